"""The PSF far beyond the optics window: where a strong laser still saturates pixels.

The design window (``optics.focal_n`` samples, 3.46 mm by default) holds ~87 % of the published mask's light; the
rest lands out to the sensor's edges at 1e-6 .. 4e-5 of the uncoded peak, which a laser of alpha_l >= 1e5 raises
to saturation. That light cannot come from the design pupil grid: its far field repeats with period
lambda f / pupil_pitch (6.98 mm by default), so beyond the window it would only show the replicas of the core.

``far_psf`` evaluates the mask on a pupil grid ``k`` times finer (each family's own ``on_grid``: analytic
families evaluate their formula, a plate keeps its cells) so that the period lambda f / pitch holds the whole
reach the laser needs, and propagates with one zero-padded FFT whose native pitch is at most the sensor pitch.
Computed without gradient: it is the laser's distant halo, refreshed by the camera (codesign/camera/camera.py).
"""
from __future__ import annotations

import math

import torch

from codesign.optics.propagation import next_fast_len
from codesign.optics.psf import OpticalSystem
from codesign.optics.spec import OpticsSpec


def far_spec(spec: OpticsSpec, reach_m: float, refine: int | None = None) -> OpticsSpec:
    """The optics of the far PSF: a pupil pitch spec.pupil_pitch_m / k (k = ``refine``, or the smallest integer
    whose period lambda f / pitch is >= 2 ``reach_m``) and a square FFT plane of L samples at pitch
    q = lambda f / (L pitch) <= spec.focal_pitch_m, which covers one period: +-``reach_m`` around the spot."""
    k = refine or max(1, math.ceil(2 * reach_m / spec.replica_period_m - 1e-9))
    pitch = spec.pupil_pitch_m / k
    period = spec.lambda_f / pitch
    n = next_fast_len(math.ceil(period / spec.focal_pitch_m - 1e-9))
    return spec.replace(pupil_pitch_m=pitch, pupil_n=None, focal_n=n, focal_pitch_m=period / n, propagator="fft",
                        fft_n=n, laser_wavelengths_m=None, scene_spectrum=None)


@torch.no_grad()
def far_psf(mask, spec: OpticsSpec, reach_m: float, dtype=torch.float32, refine: int | None = None,
            phase_map=None) -> tuple:
    """(psf, pitch): the unit-energy PSF of ``mask`` (designed on ``spec``) on the far plane of ``far_spec``,
    (L, L) energy fractions per sample of side ``pitch`` [m], the optical axis at index L // 2. ``phase_map``: a
    function of the mask's phase giving the phase the light sees (a laser line's, with ``spec`` at that line)."""
    fs = far_spec(spec, reach_m, refine)
    system = OpticalSystem(fs, dtype=dtype, device=mask.grid.rho.device)
    sampled = mask.on_grid(system.grid, spec.aperture_diameter_m)
    phase = sampled.phase().detach().to(dtype)
    psf = system.psf(phase if phase_map is None else phase_map(phase), sampled.plate_cell_m)
    return psf, fs.focal_pitch_m
