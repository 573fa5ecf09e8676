"""The per-pixel (freeform) phase: a learnable phase at every pupil sample inside the aperture.

Physically a continuous phase surface through the sample values: on another pupil grid (a finer one, to check that
the design grid resolves it) the phase is interpolated bilinearly, with each neighbour's phase taken within pi of
its cell's first corner, so that 2 pi wraps (which leave the field exp(i phi) unchanged) interpolate correctly.
A design whose neighbouring samples differ by more than pi is not resolved by its grid: the finer-grid check then
disagrees, and ``max_step`` reports it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import torch

from codesign.errors import require_choice, require_number
from codesign.optics.grid import PupilGrid
from codesign.optics.masks.base import Mask, MaskSpec

STARTS = ("published", "zero", "defocus")


@dataclass(frozen=True)
class PixelSpec(MaskSpec):
    """init: published (the published half-ring phase under init_convention), zero, defocus (phi = defocus_rad
    (rho / R)^2: a near flat-top PSF, the best start of a search) or the path of a mask record (any family: its
    phase on this grid); defocus_rad [rad at the aperture edge]."""

    kind: str = "pixel"
    init: str | None = "published"
    init_convention: str = "atan2"
    defocus_rad: float = 40.0

    def __post_init__(self) -> None:
        super().__post_init__()
        require_choice(f"{self.prefix}.init_convention", self.init_convention, ("atan", "atan2"))
        require_number(f"{self.prefix}.defocus_rad", self.defocus_rad, lo=-1e4, hi=1e4)


class PixelPhaseMask(Mask):
    """A learnable phase [rad] at every support sample of the pupil grid (``values``).

    ``project()`` wraps the phase into [-pi, pi): a phase plate is built modulo 2 pi, and the wrap leaves the field
    exp(i phi) unchanged.
    """

    kind = "pixel"
    Spec = PixelSpec
    resolution_step = 1.0  # rad: a phase per sample learns structure between samples unless its steps are capped
    fits_phases = True
    search_start = "defocus"

    def __init__(self, grid: PupilGrid, init_phase: torch.Tensor | None = None, levels: int | None = None):
        super().__init__(grid, levels)
        n_s = grid.support.numel()
        if init_phase is None:
            values = torch.zeros(n_s, dtype=grid.rho.dtype, device=grid.rho.device)
        else:
            if tuple(init_phase.shape) != (grid.n, grid.n):
                raise ValueError(f"mask.init phase has shape {tuple(init_phase.shape)}, the pupil grid is "
                                 f"{grid.n} x {grid.n}")
            values = init_phase.detach().reshape(-1)[grid.support].to(grid.rho)
        if not bool(torch.isfinite(values).all()):
            raise ValueError("mask.init phase holds NaN or Inf inside the aperture")
        self.values = torch.nn.Parameter(values.clone())

    def support_phase(self) -> torch.Tensor:
        return self.values

    @torch.no_grad()
    def project(self) -> None:
        self.values.add_(math.pi).remainder_(2 * math.pi).sub_(math.pi)

    @torch.no_grad()
    def fit_phase(self, phase: torch.Tensor) -> None:
        self.values.copy_(phase.detach().reshape(-1)[self.grid.support].to(self.values))

    # ---- the family interface -------------------------------------------------------------------------------------
    def bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        # the phase is periodic: any box works; a finite one keeps every nlopt algorithm's move limits defined
        n = self.vector_size
        return torch.full((n,), -1e4, dtype=torch.float64), torch.full((n,), 1e4, dtype=torch.float64)

    def parameter_values(self) -> dict[str, Any]:  # 125k numbers: float32 precision is what the plate holds
        return {"values": [float(f"{v:.7g}") for v in self.values.detach().cpu().tolist()]}

    def settings(self) -> dict[str, Any]:
        return {"grid_n": self.grid.n, "pitch_m": self.grid.pitch}

    def max_step(self) -> float:
        """Largest phase difference [rad] between horizontally or vertically neighbouring support samples, each
        taken modulo 2 pi into [0, pi]: above ~pi / 2 the grid under-samples the surface."""
        phase = self.phase().detach().to(torch.float64)
        inside = self.grid.aperture > 0
        worst = 0.0
        for d, both in ((phase.diff(dim=1), inside[:, 1:] & inside[:, :-1]),
                        (phase.diff(dim=0), inside[1:, :] & inside[:-1, :])):
            step = (torch.remainder(d + math.pi, 2 * math.pi) - math.pi).abs()
            if bool(both.any()):
                worst = max(worst, float(step[both].max()))
        return worst

    def on_grid(self, grid: PupilGrid, aperture_diameter_m: float) -> "PixelPhaseMask":
        return PixelPhaseMask(grid, interpolate_phase(self.phase().detach(), self.grid, grid),
                              levels=self.levels).freeze()

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], grid: PupilGrid, aperture_diameter_m: float,
                    start_phase: torch.Tensor | None = None, prefix: str = "mask") -> "PixelPhaseMask":
        """``start_phase``: the (n, n) phase of a loaded record (any family) on this grid; else ``init``."""
        if start_phase is None:
            init = require_choice(f"{prefix}.init", cfg.get("init", PixelSpec.init), STARTS)
            start_phase = start(init, grid, aperture_diameter_m, cfg)
        return cls(grid, start_phase, levels=cfg.get("levels"))


def start(name: str, grid: PupilGrid, aperture_diameter_m: float, cfg: Mapping[str, Any]) -> torch.Tensor | None:
    """The (n, n) phase of a named start: published (half-ring), zero (None) or defocus."""
    if name == "zero":
        return None
    if name == "defocus":
        a = require_number("mask.defocus_rad", cfg.get("defocus_rad", PixelSpec.defocus_rad), lo=-1e4, hi=1e4)
        return a * (grid.rho / (aperture_diameter_m / 2)) ** 2
    from codesign.optics.masks.halfring import (
        HalfRingMask,  # the published preset's phase
    )

    conv = require_choice("mask.init_convention", cfg.get("init_convention", PixelSpec.init_convention),
                          ("atan", "atan2"))
    return HalfRingMask(grid, aperture_diameter_m, convention=conv).freeze().phase().detach()


def interpolate_phase(phase: torch.Tensor, src: PupilGrid, dst: PupilGrid) -> torch.Tensor:
    """A phase sampled on grid ``src`` (n, n), bilinearly interpolated at the samples of grid ``dst`` (wrap-aware:
    the corners of each cell are taken within pi of its first corner). Samples of ``dst`` beyond ``src``'s support
    take the nearest support sample's phase (the aperture is ~0 there)."""
    ph = phase.detach().to(torch.float64)
    ph = fill_outside(ph, src)
    n = src.n
    scale = dst.pitch / src.pitch
    pos = (torch.arange(dst.n, dtype=torch.float64, device=ph.device) - dst.n // 2) * scale + n // 2
    pos = pos.clamp(0, n - 1)
    i0 = pos.floor().clamp(max=n - 2).long()
    f = pos - i0
    a = ph[i0][:, i0]
    wrap = lambda x: torch.remainder(x + math.pi, 2 * math.pi) - math.pi  # noqa: E731
    b = a + wrap(ph[i0][:, i0 + 1] - a)
    c = a + wrap(ph[i0 + 1][:, i0] - a)
    d = a + wrap(ph[i0 + 1][:, i0 + 1] - a)
    fy, fx = f[:, None], f[None, :]
    out = a * (1 - fy) * (1 - fx) + b * (1 - fy) * fx + c * fy * (1 - fx) + d * fy * fx
    return out.to(phase.dtype)


def fill_outside(ph: torch.Tensor, grid: PupilGrid) -> torch.Tensor:
    """The phase with every sample outside the support set to its nearest support sample's (along rows, then
    columns, repeatedly): interpolation near the aperture edge then never mixes in the zeros outside."""
    inside = torch.zeros(grid.n * grid.n, dtype=torch.bool, device=ph.device)
    inside[grid.support] = True
    inside = inside.reshape(grid.n, grid.n)
    out = ph.clone()
    filled = inside.clone()
    for _ in range(grid.n):
        if bool(filled.all()):
            break
        grown = filled.clone()
        for dim, step in ((0, 1), (0, -1), (1, 1), (1, -1)):
            src_ok = torch.roll(filled, step, dims=dim)
            take = ~grown & src_ok
            out = torch.where(take, torch.roll(out, step, dims=dim), out)
            grown = grown | take
        filled = grown
    return out
