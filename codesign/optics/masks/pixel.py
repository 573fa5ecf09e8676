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

from codesign.errors import ConfigError, require_choice, require_number
from codesign.optics.grid import PupilGrid
from codesign.optics.masks.base import NAMED_STARTS, Mask, PhaseFitSpec, fill_outside, require_phases
from codesign.optics.masks.starts import named_start
from codesign.optics.spec import OpticsSpec

@dataclass(frozen=True)
class PixelSpec(PhaseFitSpec):
    """init: published (the published half-ring phase under init_convention), zero, defocus (phi = defocus_rad
    (rho / R)^2: a near flat-top PSF, the best start of a search) or the path of a mask record (any family: its
    phase on this grid)."""

    kind: str = "pixel"
    init: str | None = "published"


class PixelPhaseMask(Mask):
    """A learnable phase [rad] at every support sample of the pupil grid (``values``).

    ``project()`` wraps the phase into [-pi, pi): a phase plate is built modulo 2 pi, and the wrap leaves the field
    exp(i phi) unchanged.
    """

    kind = "pixel"
    record_values = {"values": "list", "grid_n": "number", "pitch_m": "number"}
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
        """The plate's cell width [m]: one pupil sample (the phase is constant over each)."""
        return self.grid.pitch

    def support_phase(self) -> torch.Tensor:
        """The phase [rad] of every support sample: the parameters themselves."""
        return self.values

    @torch.no_grad()
    def project(self) -> None:
        """Wrap every sample's phase into [-pi, pi) (the plate holds it modulo 2 pi)."""
        self.values.add_(math.pi).remainder_(2 * math.pi).sub_(math.pi)

    @torch.no_grad()
    def fit_phase(self, phase: torch.Tensor) -> None:
        """Take a full-grid (n, n) phase [rad] at the support samples as the parameters."""
        self.values.copy_(phase.detach().reshape(-1)[self.grid.support].to(self.values))

    # ---- the family interface -------------------------------------------------------------------------------------
    def bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(lower, upper): +-1e4 rad for every sample (float64)."""
        # the phase is periodic: any box works; a finite one keeps every nlopt algorithm's move limits defined
        n = self.vector_size
        return torch.full((n,), -1e4, dtype=torch.float64), torch.full((n,), 1e4, dtype=torch.float64)

    def parameter_values(self) -> dict[str, Any]:  # 125k numbers: float32 precision is what the plate holds
        """The samples' phases [rad] at 7 significant digits, JSON-ready."""
        return {"values": [float(f"{v:.7g}") for v in self.values.detach().cpu().tolist()]}

    def settings(self) -> dict[str, Any]:
        """The plate's grid: its samples across (grid_n) and pitch [m]."""
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
        """The same plate resampled onto another pupil grid, frozen."""
        return PixelPhaseMask(grid, resample_plate(self.phase().detach(), self.grid, grid),
                              levels=self.levels).freeze()

    @classmethod
    def check_record(cls, record: Mapping[str, Any], prefix: str) -> None:
        """Check a pixel record (mask.init=PATH) under ``prefix``: its grid and values; ConfigError naming the key
        otherwise."""
        check_plate(record, prefix)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], grid: PupilGrid, aperture_diameter_m: float,
                    record: dict | None = None, start_phase: torch.Tensor | None = None,
                    prefix: str = "mask") -> "PixelPhaseMask":
        """``record``: a pixel record (its plate, sampled on this grid); ``start_phase``: the (n, n) phase of
        another family's record on this grid; else ``init``."""
        if record is not None:
            start_phase = record_plate(record, grid)
        elif start_phase is None:
            init = require_choice(f"{prefix}.init", cfg.get("init", PixelSpec.init), NAMED_STARTS)
            start_phase = named_start(init, grid, aperture_diameter_m, cfg, prefix)
        return cls(grid, start_phase, levels=cfg.get("levels"))


def support_size(n: int, pitch: float, radius_m: float) -> int:
    """How many samples of an n x n grid at ``pitch`` lie within ``radius_m`` of the axis: PupilGrid.from_spec's
    support, with its comparison, counted on the box around the disk only (a record's grid is never allocated)."""
    half = min(n // 2, int(radius_m / pitch) + 1)
    k = torch.arange(-half, min(n - n // 2 - 1, half) + 1)
    r2_max = (radius_m / pitch) ** 2
    return sum(int(((rows[:, None] ** 2 + k[None, :] ** 2).reshape(-1) <= r2_max).sum()) for rows in k.split(256))


def record_spec(record: Mapping[str, Any], prefix: str = "optics") -> OpticsSpec:
    """The optics a pixel record's grid belongs to: its ``optics`` (defaults where it has none) at its pitch."""
    optics = record.get("optics") or {}
    fields = {k: optics[k] for k in ("wavelength_m", "focal_length_m", "aperture_diameter_m",
                                      "supergaussian_order") if k in optics}
    return OpticsSpec(**fields, pupil_pitch_m=float(record["pitch_m"]), focal_n=8, focal_pitch_m=1e-9, prefix=prefix)


def check_plate(record: Mapping[str, Any], prefix: str) -> None:
    """A pixel record's grid (grid_n, pitch_m: the optics.pupil_* rules, and the grid holds the aperture) and one
    value per sample of its support, each a phase within +-PHASE_LIMIT."""
    n = require_number(f"{prefix}.grid_n", record["grid_n"], lo=2, hi=65536, integer=True)
    require_number(f"{prefix}.pitch_m", record["pitch_m"], lo=0, lo_open=True)
    spec = record_spec(record, f"{prefix}.optics")
    if n < spec.min_pupil_n:
        raise ConfigError(f"{prefix}.grid_n", n, f"its grid ({n} x {spec.pupil_pitch_m:.3g} m) cannot hold the "
                          f"aperture (W_a = {spec.aperture_diameter_m:.4g} m): must be >= {spec.min_pupil_n}")
    values = record["values"]
    radius = spec.aperture_support_radius_m
    box = (2 * min(n // 2, radius / spec.pupil_pitch_m + 1) + 1) ** 2
    # counted when the box is at most ~10x the largest record's values (a tiny pitch_m: estimated, never counted)
    count = support_size(n, spec.pupil_pitch_m, radius) if box <= 2**25 else None
    if count != len(values):
        size = f"{count}" if count is not None else f"about {math.pi * (radius / spec.pupil_pitch_m) ** 2:.3g}"
        raise ConfigError(f"{prefix}.values", values, f"must hold one phase per sample of its grid inside the "
                          f"aperture ({size} for grid_n = {n}, pitch_m = {spec.pupil_pitch_m:g}), it holds "
                          f"{len(values)}")
    require_phases(f"{prefix}.values", values)


def record_plate(record: dict, grid: PupilGrid) -> torch.Tensor:
    """The (n, n) phase on ``grid`` of a pixel record's plate (designed on another grid: sampled there, cell by
    cell)."""
    values = torch.tensor(record["values"], dtype=torch.float64)
    if int(record["grid_n"]) == grid.n and abs(float(record["pitch_m"]) / grid.pitch - 1) < 1e-9 and \
            values.numel() == grid.support.numel():
        return grid.scatter(values.to(grid.rho)).detach()
    src = _record_grid(record, grid)
    if values.numel() != src.support.numel():
        raise ConfigError("mask.init", getattr(record, "path", "record"), f"holds {values.numel()} pixel values, "
                          f"its grid ({src.n} x {src.n}) has {src.support.numel()} samples in the aperture")
    return resample_plate(src.scatter(values), src, grid).to(grid.rho)


def _record_grid(record: dict, grid: PupilGrid) -> PupilGrid:
    """The pupil grid a pixel record was designed on (its optics, the defaults where it has none, at its pitch)."""
    spec = record_spec(record).replace(pupil_n=int(record["grid_n"]))
    return PupilGrid.from_spec(spec, dtype=torch.float64)


def resample_plate(phase: torch.Tensor, src: PupilGrid, dst: PupilGrid) -> torch.Tensor:
    """The phase of the plate whose cells are grid ``src``'s samples (n, n), at the samples of grid ``dst``: each
    takes the phase of the cell it lies in (nearest sample; both grids centred on the axis). Samples of ``dst``
    beyond ``src``'s support take the nearest support cell's phase (the aperture is ~0 there)."""
    ph = fill_outside(phase.detach().to(torch.float64), src)
    pos = (torch.arange(dst.n, dtype=torch.float64, device=ph.device) - dst.n // 2) * (dst.pitch / src.pitch)
    # floor(x + 1/2) with a relative nudge: a sample on a cell's edge (even refinements) goes one way, always
    idx = (torch.floor(pos + 0.5 + 1e-9) + src.n // 2).clamp(0, src.n - 1).long()
    return ph[idx][:, idx].to(phase.dtype)
