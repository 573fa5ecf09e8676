"""Differentiable optics: pupil grid, Bessel J_n, phase masks, propagation, PSF, LSR/BSR/MTF."""
from codesign.optics.bessel import bessel_j
from codesign.optics.grid import PupilGrid
from codesign.optics.masks import (
    HalfRingMask,
    Mask,
    PixelPhaseMask,
    SpiralMask,
    ZernikeMask,
    build_mask,
)
from codesign.optics.metrics import (
    RadialMTF,
    bsr,
    circular_mtf,
    lsr_sampled,
    lsr_smooth,
    mtf,
    otf,
)
from codesign.optics.psf import OpticalSystem, airy_psf, pupil_field
from codesign.optics.spec import OpticsSpec

__all__ = [
    "OpticsSpec", "PupilGrid", "OpticalSystem", "Mask", "HalfRingMask", "PixelPhaseMask", "SpiralMask", "ZernikeMask",
    "build_mask", "bessel_j", "airy_psf", "pupil_field", "lsr_sampled", "lsr_smooth", "bsr", "otf", "mtf",
    "RadialMTF", "circular_mtf",
]
