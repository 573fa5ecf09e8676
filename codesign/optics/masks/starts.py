"""The named starts of the families that fit any phase (``Mask.fits_phases``): mask.init=published | zero | defocus.
Apart from base.py because the published start is the half-ring family's phase (base.py imports no family)."""
from __future__ import annotations

from typing import Any, Mapping

import torch

from codesign.optics.grid import PupilGrid
from codesign.optics.masks.base import PhaseFitSpec
from codesign.optics.masks.halfring import HalfRingMask


def named_start(name: str, grid: PupilGrid, aperture_diameter_m: float, settings: Mapping[str, Any],
                prefix: str = "mask") -> torch.Tensor | None:
    """The (n, n) phase of a named start of a phase-fitting family: published (the half-ring phase under
    ``settings``'s init_convention), zero (None) or defocus (``settings``'s defocus_rad)."""
    spec = PhaseFitSpec(**{k: settings[k] for k in ("init_convention", "defocus_rad") if k in settings}, prefix=prefix)
    if name == "zero":
        return None
    if name == "defocus":
        return spec.defocus_rad * (grid.rho / (aperture_diameter_m / 2)) ** 2
    return HalfRingMask(grid, aperture_diameter_m, convention=spec.init_convention).freeze().phase().detach()
