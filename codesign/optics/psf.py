"""Coded and uncoded PSFs (Eq. 3-4): pupil field A exp(i phi) -> unit-energy PSF on the sensor-pitch window.

Normalization: ``psf[k]`` is the fraction of the total transmitted energy that falls on focal pixel k (the
irradiance at the pixel centre times the pixel area), so the PSF sums to 1 over the whole focal plane and to
``psf_energy_in_window`` over the window. Coded and uncoded PSFs thus have equal energy, as the LSR needs.

A pixelated plate (a phase constant over square cells of width c, the pixel family) is exact on a grid of one
sample per cell: its transmission is sum_j t_j rect((x - x_j) / c), whose far field is the sampled pupil's DFT
times sinc(c x / (lambda f)) sinc(c y / (lambda f)). ``psf(phase, cell_m=c)`` applies that envelope: no aliasing,
and the light the plate sends to high angles is attenuated there as it is in the lab.
"""
from __future__ import annotations

import math

import torch

from codesign.optics.grid import PupilGrid, axis_coords
from codesign.optics.peak import Peak, PeakSearch
from codesign.optics.propagation import Propagator
from codesign.optics.spec import OpticsSpec


def pupil_field(aperture: torch.Tensor, phase: torch.Tensor) -> torch.Tensor:
    """A exp(i phi): complex pupil field of the aperture amplitude and phase [rad], same shape."""
    return torch.polar(aperture, phase)


def airy_psf(r: torch.Tensor, spec: OpticsSpec) -> torch.Tensor:
    """Analytic unit-energy uncoded PSF of a hard circular aperture (Eq. 3) at radii r [m], per focal pixel.

    h0(r) = h0(0) [2 J1(v) / v]^2 with v = pi W_a r / (lambda f) and h0(0) = (pi W_a^2 / 4) dx^2 / (lambda f)^2.
    """
    from codesign.optics.bessel import (
        bessel_j,  # local: avoids a cycle for users that only need the grid
    )

    v = math.pi * spec.aperture_diameter_m * r / spec.lambda_f
    j1 = bessel_j(v, 1)[..., 1]
    safe_v = torch.where(v > 0, v, torch.ones_like(v))
    shape = torch.where(v > 0, 2 * j1 / safe_v, torch.ones_like(v)) ** 2
    peak = math.pi * spec.aperture_diameter_m**2 / 4 * spec.focal_pitch_m**2 / spec.lambda_f**2
    return peak * shape


# Sub-sample offsets (in focal samples) of the extra grids a smooth LSR sees, by number of grids
# (metrics.lsr_grids). Every point lies within 0.71 / 0.5 / 0.35 samples of one of them with 1 / 2 / 4 grids, which
# caps how far below a peak the samples can read (codesign.optics.peak: the shortfall goes with that distance^2).
SUBSAMPLE_SHIFTS = {1: (), 2: ((0.5, 0.5),), 4: ((0.5, 0.5), (0.5, 0.0), (0.0, 0.5))}


class OpticalSystem(torch.nn.Module):
    """A sampled pupil plus a propagator onto the sensor-pitch focal window.

    Args:
        spec: the validated optics parameters.
        dtype: float32 or float64 (complex64/complex128 fields).
        method: propagator override ("mft" or "fft"); default: ``spec.propagator`` resolved by cost.
    """

    def __init__(self, spec: OpticsSpec, dtype=torch.float32, device=None, method: str | None = None):
        super().__init__()
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"OpticalSystem dtype must be torch.float32 or torch.float64, got {dtype}")
        self.spec = spec
        self.dtype = dtype
        self.grid = PupilGrid.from_spec(spec, dtype=dtype, device=device)
        self.propagator = Propagator(spec, method=method, dtype=dtype, device=device)
        a = self.grid.aperture.to(torch.float64)
        # On-axis value of the uncoded PSF, exact on this grid: E0(0) = sum A, so h0(0) = (sum A)^2 s / sum A^2.
        scale = (spec.pupil_pitch_m * spec.focal_pitch_m / spec.lambda_f) ** 2
        self.uncoded_peak = float(a.sum() ** 2 * scale / (a**2).sum())
        self._uncoded_energy = None
        self._envelopes: dict[float, torch.Tensor] = {}
        self._peak_search = None

    @property
    def uncoded_energy(self) -> float:
        """Energy of the uncoded PSF inside the focal window (computed once, on first use)."""
        if self._uncoded_energy is None:
            with torch.no_grad():
                self._uncoded_energy = float(self.uncoded_psf().sum())
        return self._uncoded_energy

    @property
    def method(self) -> str:
        """The propagator in use (mft, czt or fft: optics.propagator, auto resolved by modelled cost)."""
        return self.propagator.method

    def field(self, phase: torch.Tensor) -> torch.Tensor:
        """Complex pupil field for a (..., n, n) phase [rad]."""
        return pupil_field(self.grid.aperture, phase)

    def psf(self, phase: torch.Tensor, cell_m: float | None = None) -> torch.Tensor:
        """Unit-energy coded PSF (..., m, m) on the focal window for a (..., n, n) phase [rad]; ``cell_m``: the
        phase is a plate of square cells of this width (one per pupil sample), None: point samples of a smooth
        surface."""
        psf = self.propagator.intensity(self.field(phase))
        return psf if cell_m is None else psf * self.cell_envelope(cell_m).to(psf)

    def mask_psf(self, mask) -> torch.Tensor:
        """``psf`` of a mask's phase, with its plate cell (``mask.plate_cell_m``)."""
        return self.psf(mask.phase(), mask.plate_cell_m)

    def cell_envelope(self, cell_m: float, coords: torch.Tensor | None = None) -> torch.Tensor:
        """sinc^2(c x / (lambda f)) sinc^2(c y / (lambda f)) at the window's samples (m, m), float64; or, with
        ``coords`` (k,), the 1-D factor at those focal coordinates [m]."""
        if not (isinstance(cell_m, (int, float)) and math.isfinite(cell_m) and cell_m > 0):
            raise ValueError(f"a plate cell must be a positive width in m, got {cell_m!r}")
        if coords is not None:
            return torch.sinc(coords.to(torch.float64) * (cell_m / self.spec.lambda_f)) ** 2
        key = float(cell_m)
        if key not in self._envelopes:
            s = self.cell_envelope(key, axis_coords(self.spec.focal_n, self.spec.focal_pitch_m,
                                                    device=self.grid.rho.device))
            self._envelopes[key] = s[:, None] * s[None, :]
        return self._envelopes[key]

    def shifted_psf(self, phase: torch.Tensor, shift: tuple[float, float], cell_m: float | None = None) -> torch.Tensor:
        """``psf`` at the window's samples moved by ``shift`` = (dy, dx) focal samples: the continuous PSF between
        the samples, exact for every propagator (E(x + s) is the field of the pupil tilted by -2 pi s u / (lambda
        f)). Differentiable in ``phase``."""
        s = self.spec
        k = -2 * math.pi * s.focal_pitch_m / s.lambda_f
        tilt = k * (shift[0] * self.grid.v[:, None] + shift[1] * self.grid.u[None, :])
        psf = self.propagator.intensity(self.field(phase + tilt.to(phase.dtype)))
        if cell_m is None:
            return psf
        coords = axis_coords(s.focal_n, s.focal_pitch_m, device=self.grid.rho.device)
        ey = self.cell_envelope(cell_m, coords + shift[0] * s.focal_pitch_m)
        ex = self.cell_envelope(cell_m, coords + shift[1] * s.focal_pitch_m)
        return psf * (ey[:, None] * ex[None, :]).to(psf)

    def lsr_samples(self, phase: torch.Tensor, psf: torch.Tensor, grids: int, cell_m: float | None = None
                    ) -> torch.Tensor:
        """The PSF samples a smooth LSR is taken over, (..., grids * m, m): the window's samples (``psf``, already
        computed) and, for ``grids`` 2, the grid offset by half a sample along both axes, for 4, by half a sample
        along either or both (SUBSAMPLE_SHIFTS). An optimizer that flattens the samples cannot hide a peak midway
        between them from these."""
        if grids not in SUBSAMPLE_SHIFTS:
            raise ValueError(f"lsr grids must be one of {sorted(SUBSAMPLE_SHIFTS)}, got {grids!r}")
        extra = [self.shifted_psf(phase, sh, cell_m) for sh in SUBSAMPLE_SHIFTS[grids]]
        return torch.cat([psf, *extra], dim=-2) if extra else psf

    def uncoded_psf(self) -> torch.Tensor:
        """The uncoded PSF h0 computed through the same propagator (zero phase), (m, m)."""
        return self.psf(torch.zeros_like(self.grid.aperture))

    @torch.no_grad()
    def continuous_peak(self, phase: torch.Tensor, cell_m: float | None = None, rel_tol: float = 3e-3) -> Peak:
        """The peak of the continuous PSF on the window (per-pixel units), certified to ``rel_tol`` between samples
        (codesign.optics.peak): the irradiance a sensor pixel at the worst place receives. ``cell_m``: as in
        ``psf``."""
        if self._peak_search is None:
            s = self.spec
            self._peak_search = PeakSearch(axis_coords(self.grid.n, s.pupil_pitch_m, device=self.grid.rho.device),
                                           s.lambda_f, s.focal_pitch_m, s.focal_n, self.grid.aperture,
                                           s.pupil_pitch_m)
        return self._peak_search(self.field(phase.detach()), cell_m, rel_tol)

    def continuous_lsr(self, phase: torch.Tensor, cell_m: float | None = None) -> float:
        """The LSR every report gives: the certified continuous peak (``continuous_peak``) over the uncoded peak."""
        return self.continuous_peak(phase, cell_m=cell_m).value / self.uncoded_peak
