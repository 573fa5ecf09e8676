"""The spiral (vortex axicon) phase, a classical anti-dazzle reference design.

    phi(rho, Phi) = charge * Phi + 2 pi axicon_cycles * rho / R + defocus_rad * (rho / R)^2,   R = W_a / 2.

A vortex of topological charge l puts a zero on the optical axis and spreads the focal spot into a ring of radius
~ l lambda f / (pi W_a); the axicon term moves the light to a ring of radius 2 axicon_cycles lambda f / W_a; the
defocus term widens it. Vortex and axicon phase plates are reported in the anti-dazzle literature as lowering the
laser's peak irradiance below 1 % of the unmasked peak; here the three coefficients are free, continuous
parameters (a non-integer charge leaves a phase step along Phi = pi, which a plate can hold). Phi is the pupil
grid's polar angle (measured from +v towards +u).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import torch

from codesign.errors import ConfigError, require_number, require_numbers
from codesign.optics.grid import PupilGrid
from codesign.optics.masks.base import Mask, MaskSpec

NAMES = ("charge", "axicon_cycles", "defocus_rad")
BOUND_KEYS = ("charge_bounds", "axicon_bounds", "defocus_bounds")


def check_box(pair, key: str) -> tuple[float, float]:
    """[lo, hi] with -1e4 <= lo < hi <= 1e4: the box of one coefficient."""
    lo, hi = require_numbers(key, pair, "must be [lo, hi] with lo < hi", 2, lo=-1e4, hi=1e4)
    if lo >= hi:
        raise ConfigError(key, [lo, hi], "must be [lo, hi] with lo < hi")
    return lo, hi


@dataclass(frozen=True)
class SpiralSpec(MaskSpec):
    """charge: topological charge l (a real number); axicon_cycles: phase cycles from the centre to the aperture
    edge; defocus_rad: quadratic phase at the edge [rad]; bounds: [lo, hi] of each, the box a search explores and
    project() clamps into (chosen so that a 384-sample pupil grid resolves the phase: well below one cycle per two
    samples, and so that the axicon ring, at 2 axicon_cycles lambda f / W_a, stays inside a 640-pixel window)."""

    kind: str = "spiral"
    init: str | None = None
    charge: float = 3.0
    axicon_cycles: float = 10.0
    defocus_rad: float = 0.0
    charge_bounds: tuple = (-60.0, 60.0)
    axicon_bounds: tuple = (-40.0, 40.0)
    defocus_bounds: tuple = (-150.0, 150.0)


class SpiralMask(Mask):
    """Learnable ``coeffs`` = [charge, axicon_cycles, defocus_rad]; see the module docstring."""

    kind = "spiral"
    record_values = {"charge": "number", "axicon_cycles": "number", "defocus_rad": "number"}
    record_settings = ("charge_bounds", "axicon_bounds", "defocus_bounds")
    Spec = SpiralSpec
    search_start = "mask"  # the configured spiral: the family has no published member

    def __init__(self, grid: PupilGrid, aperture_diameter_m: float, charge: float = SpiralSpec.charge,
                 axicon_cycles: float = SpiralSpec.axicon_cycles, defocus_rad: float = SpiralSpec.defocus_rad,
                 bounds: tuple = (SpiralSpec.charge_bounds, SpiralSpec.axicon_bounds, SpiralSpec.defocus_bounds),
                 prefix: str = "mask", levels: int | None = None):
        super().__init__(grid, levels)
        values = [require_number(f"{prefix}.{k}", v, lo=-1e4, hi=1e4) for k, v in
                  zip(NAMES, (charge, axicon_cycles, defocus_rad))]
        self.box = [check_box(pair, f"{prefix}.{key}") for key, pair in zip(BOUND_KEYS, bounds)]
        self.aperture_diameter_m = aperture_diameter_m
        dtype, device = grid.rho.dtype, grid.rho.device
        rho = grid.rho.reshape(-1)[grid.support] / (aperture_diameter_m / 2)
        basis = torch.stack([grid.angle.reshape(-1)[grid.support], 2 * math.pi * rho, rho**2])
        self.register_buffer("basis", basis.to(dtype), persistent=False)
        self.coeffs = torch.nn.Parameter(torch.tensor(values, dtype=dtype, device=device))

    def support_phase(self) -> torch.Tensor:
        """The phase [rad] at the support samples: charge, axicon and defocus coefficients times their basis."""
        return self.coeffs @ self.basis

    @torch.no_grad()
    def project(self) -> None:
        """Clamp each coefficient into its bounds."""
        lo, hi = self.bounds()
        self.coeffs.copy_(torch.maximum(torch.minimum(self.coeffs, hi.to(self.coeffs)), lo.to(self.coeffs)))

    # ---- the family interface -------------------------------------------------------------------------------------
    def bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(lower, upper) of (charge, axicon, defocus): the configured bounds (float64)."""
        return (torch.tensor([b[0] for b in self.box], dtype=torch.float64),
                torch.tensor([b[1] for b in self.box], dtype=torch.float64))

    def vector_names(self) -> list[str]:
        """The coefficients' names, in ``to_vector`` order."""
        return list(NAMES)

    def summary(self) -> dict[str, float]:
        """The coefficients as scalars, by name."""
        return dict(zip(NAMES, (float(v) for v in self.coeffs.detach().cpu())))

    def settings(self) -> dict[str, Any]:
        """The coefficients' bounds: what fixes the phase besides their values."""
        return {"charge_bounds": list(self.box[0]), "axicon_bounds": list(self.box[1]),
                "defocus_bounds": list(self.box[2])}

    def parameter_values(self) -> dict[str, Any]:
        """The coefficients by name, JSON-ready."""
        return self.summary()

    def on_grid(self, grid: PupilGrid, aperture_diameter_m: float) -> "SpiralMask":
        """The same mask on another pupil grid, frozen."""
        return SpiralMask(grid, aperture_diameter_m, *self.coeffs.detach().tolist(), bounds=tuple(self.box),
                          levels=self.levels).freeze()

    @classmethod
    def check_record(cls, record: Mapping[str, Any], prefix: str) -> None:
        """Check a spiral record (mask.init=PATH) under ``prefix``: its coefficients and bounds; ConfigError naming
        the key otherwise."""
        for k in NAMES:
            require_number(f"{prefix}.{k}", record[k], lo=-1e4, hi=1e4)
        for key in BOUND_KEYS:
            if key in record:
                check_box(record[key], f"{prefix}.{key}")

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], grid: PupilGrid, aperture_diameter_m: float,
                    record: dict | None = None, prefix: str = "mask") -> "SpiralMask":
        """The mask of a config block (its coefficients from ``record`` when given, else from the block; the bounds
        from the block)."""
        src = record if record is not None else cfg
        bounds = tuple(cfg.get(k, getattr(SpiralSpec, k)) for k in BOUND_KEYS)
        return cls(grid, aperture_diameter_m, *(src.get(k, getattr(SpiralSpec, k)) for k in NAMES), bounds=bounds,
                   prefix=prefix, levels=cfg.get("levels"))
