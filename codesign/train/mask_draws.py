"""Random masks of a family for a restorer's training pool (``data.masks: [random:FAMILY:N, ...]``).

A restorer that takes the OTF should have seen every kind of PSF it may be given: the rings of half-ring plates, the
near flat tops of defocus-like freeforms, the speckle of pixel plates, the low-order blurs of Zernike plates. A draw
is accepted when its sampled LSR (window PSF peak / unmasked peak) lies in ``data.mask_lsr`` (default 1e-4 to 1e-2,
the range of every design this project makes), so that the pool spans the laser suppression a design would have.

- families that fit any phase (spline, Zernike, pixel): a defocus of random strength (5 to 120 rad at the pupil's
  edge) plus a smooth random phase (a Gaussian random field low-passed to 1.5 to 8 cycles over the pupil, RMS 0.3
  to 20 rad, log-uniform), fitted by the family (Zernike keeps its low orders of it, a spline its smooth part, a pixel plate all);
- the others (half rings): uniform in the family's bounds.

Draws are a function of the numpy generator given (the pool's seed): a resumed run rebuilds the same pool.
"""
from __future__ import annotations

import copy
import logging
import math

import numpy as np
import torch

from codesign.errors import ConfigError
from codesign.optics.masks import FAMILIES, build_mask
from codesign.sensor.simulator import psf_state

log = logging.getLogger("codesign.train")
TRIES = 60  # draws per accepted mask before giving up (the message then names the family and the range)


def smooth_random_phase(grid, rng: np.random.Generator) -> torch.Tensor:
    """(n, n) float64: defocus (5 to 120 rad at the pupil's edge) plus a Gaussian random field of 1.5 to 8 cycles
    over the pupil and an RMS of 0.3 to 20 rad (log-uniform) over the support [rad]."""
    rho = grid.rho.to(torch.float64)
    radius = float(rho.reshape(-1)[grid.support].max())
    n = rho.shape[-1]
    cycles = rng.uniform(1.5, 8.0)
    freq = np.fft.fftfreq(n) * n * (2 * radius / (n * grid.pitch))  # cycles over the pupil's diameter
    f2 = freq[:, None] ** 2 + freq[None, :] ** 2
    noise = np.fft.ifft2(np.fft.fft2(rng.standard_normal((n, n))) * np.exp(-f2 / (2 * cycles**2))).real
    field = torch.from_numpy(noise)
    inside = field.reshape(-1)[grid.support]
    rms = math.exp(rng.uniform(math.log(0.3), math.log(20.0)))
    field = (field - inside.mean()) / inside.std().clamp_min(1e-30) * rms
    return rng.uniform(5.0, 120.0) * (rho / radius) ** 2 + field


def sampled_lsr(system, mask) -> float:
    """Window PSF peak over the unmasked peak (no certification: a pool member needs its range, not its bound)."""
    with torch.no_grad():
        state = psf_state(system, mask.phase(), mask.plate_cell_m)
    return float(state.psf.max() / state.uncoded_peak)


def random_family_masks(family: str, count: int, system, aperture_m: float, rng: np.random.Generator,
                        lsr_range: tuple[float, float], key: str = "data.masks") -> list[tuple[str, object]]:
    """``count`` frozen random masks of ``family`` on ``system``'s grid with sampled LSR in ``lsr_range``, as
    (name, mask) pairs; ConfigError naming ``key`` when TRIES draws in a row miss the range."""
    cls = FAMILIES[family]
    start = {**cls.Spec.defaults(), "kind": family}
    if cls.fits_phases:
        start["init"] = "zero"  # no fit of the published phase that the draw replaces
    mask = build_mask(start, system.grid, aperture_m, prefix=key)
    out = []
    for k in range(count):
        for _ in range(TRIES):
            if cls.fits_phases:
                mask.set_vector(mask.phase_vector(smooth_random_phase(system.grid, rng).to(mask.grid.rho.dtype)))
            else:
                mask.set_vector(mask.random_vector(rng))
            mask.project()
            lsr = sampled_lsr(system, mask)
            if lsr_range[0] <= lsr <= lsr_range[1]:
                break
        else:
            raise ConfigError(key, f"random:{family}", f"{TRIES} random {family} masks in a row missed the sampled "
                              f"LSR range {list(lsr_range)} (data.mask_lsr): widen it or drop this member")
        out.append((f"random:{family} {k + 1} (LSR {lsr:.2g})", copy.deepcopy(mask).freeze()))
    return out
