"""The per-pixel (freeform) phase: a pixelated plate, one square cell of constant phase per pupil sample.

A plate of cells is what a lithographic multi-level plate or a phase SLM is, and it is exact on its design grid:
the far field of sum_j A_j exp(i phi_j) rect((x - x_j) / c) is the sampled pupil's DFT times the cell's sinc
envelope, which the PSF applies (``plate_cell_m``, OpticalSystem.psf). Nothing is aliased, whatever the steps
between cells. On another pupil grid each sample takes the phase of the cell it falls in (``resample_plate``):
exact on a grid whose pitch is the cell width over an odd integer (centred like the design grid, each cell then
holds k x k samples), so the design check evaluates the same plate on a grid three times as fine, where only the
aperture's edge is sampled differently.
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
    fits_phases = True
    fine_factor = 3  # cells split exactly into 3 x 3 samples of a centred grid (2 x 2 would cut samples in half)
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

    @property
    def plate_cell_m(self) -> float:
        return self.grid.pitch

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
        """Largest phase difference [rad] between horizontally or vertically neighbouring cells, each taken modulo
        2 pi into [0, pi] (a plate is exact with any steps; this says how rough it is)."""
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
        return PixelPhaseMask(grid, resample_plate(self.phase().detach(), self.grid, grid),
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


def resample_plate(phase: torch.Tensor, src: PupilGrid, dst: PupilGrid) -> torch.Tensor:
    """The phase of the plate whose cells are grid ``src``'s samples (n, n), at the samples of grid ``dst``: each
    takes the phase of the cell it lies in (nearest sample; both grids centred on the axis). Samples of ``dst``
    beyond ``src``'s support take the nearest support cell's phase (the aperture is ~0 there)."""
    ph = fill_outside(phase.detach().to(torch.float64), src)
    pos = (torch.arange(dst.n, dtype=torch.float64, device=ph.device) - dst.n // 2) * (dst.pitch / src.pitch)
    # floor(x + 1/2) with a relative nudge: a sample on a cell's edge (even refinements) goes one way, always
    idx = (torch.floor(pos + 0.5 + 1e-9) + src.n // 2).clamp(0, src.n - 1).long()
    return ph[idx][:, idx].to(phase.dtype)


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
