"""How much memory the optics grids of an OpticsSpec take, estimated from its sizes alone (nothing allocated), so
that a run whose grids cannot fit is refused before any work: optics.pupil_pitch_m=1e-7 passed every check, then
allocated 12.7 GB for the pupil grid's first array and was killed by the operating system.

Per pupil sample: GRID_BYTES for building the grid (codesign/optics/grid.py: int64 squared radii, float64 radii,
aperture and angle, their copies in the working precision); per wavelength (each laser line and scene-spectrum
sample: a system of its own) the complex pupil field and its phase, the complex focal field and its intensity, the
propagator's two complex MFT matrices (focal_n x pupil_n) or the zero-padded FFT plane and its spectrum.
"""
from __future__ import annotations

from dataclasses import dataclass

from codesign.optics.propagation import choose_propagator, default_fft_size, exact_fft_size
from codesign.optics.spec import OpticsSpec

GRID_BYTES = 40  # per pupil sample while the grid is built (five 8-byte arrays at once)


@dataclass(frozen=True)
class GridEstimate:
    """bytes: the estimate; key: the optics key that drives it most; the sizes the message names."""

    bytes: int
    key: str
    pupil_n: int
    focal_n: int
    wavelengths: int
    complex_name: str


def grid_estimate(spec: OpticsSpec, double: bool = False) -> GridEstimate:
    """The optics grids' memory for ``spec`` in float32 (complex64) or, with ``double``, float64 (complex128)."""
    real = 8 if double else 4
    cplx = 2 * real
    n, m = spec.grid_n, spec.focal_n
    waves = len(spec.laser_lines) + len(spec.scene_spectrum or ())
    if choose_propagator(spec) == "fft":
        k = spec.fft_n or exact_fft_size(spec) or default_fft_size(spec)
        propagator = 2 * k * k * cplx
    else:
        propagator = 2 * m * n * cplx
    pupil = n * n * GRID_BYTES + waves * n * n * (cplx + real)
    focal = waves * (m * m * (cplx + real) + propagator)
    if pupil >= focal:
        key = "optics.pupil_n" if spec.pupil_n is not None else "optics.pupil_pitch_m"
    else:
        key = "optics.focal_n"
    return GridEstimate(int(pupil + focal), key, n, m, waves, "complex128" if double else "complex64")
