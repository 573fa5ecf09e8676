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
from codesign.optics.propagation import Propagator, mft, mft_matrix
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

    @property
    def uncoded_energy(self) -> float:
        """Energy of the uncoded PSF inside the focal window (computed once, on first use)."""
        if self._uncoded_energy is None:
            with torch.no_grad():
                self._uncoded_energy = float(self.uncoded_psf().sum())
        return self._uncoded_energy

    @property
    def method(self) -> str:
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

    def uncoded_psf(self) -> torch.Tensor:
        """The uncoded PSF h0 computed through the same propagator (zero phase), (m, m)."""
        return self.psf(torch.zeros_like(self.grid.aperture))

    @torch.no_grad()
    def refined_peak(self, phase: torch.Tensor, psf: torch.Tensor, candidates: int = 8,
                     oversample: int = 8, cell_m: float | None = None) -> float:
        """Peak of the continuous PSF (per-pixel units), refined between samples around the top local maxima.

        The sampled PSF can miss its maximum by up to a fraction of a sample; evaluating the field with a small
        MFT at pitch dx / oversample over +-1 sample around each of the ``candidates`` highest local maxima
        gives the continuous peak (the physical irradiance peak that damages a sensor). ``cell_m``: as in ``psf``.
        """
        s = self.spec
        p = psf.detach().reshape(s.focal_n, s.focal_n)
        pooled = torch.nn.functional.max_pool2d(p[None, None], 3, stride=1, padding=1)[0, 0]
        is_max = (p == pooled) & (p > 0)
        vals = torch.where(is_max, p, torch.zeros_like(p)).reshape(-1)
        top = torch.topk(vals, min(candidates, vals.numel())).indices
        field = self.field(phase.detach())
        pupil = axis_coords(self.grid.n, s.pupil_pitch_m, device=p.device)
        off = torch.arange(-oversample, oversample + 1, dtype=torch.float64, device=p.device) / oversample
        cdtype = field.dtype
        best = float(p.max())
        scale = (s.pupil_pitch_m * s.focal_pitch_m / s.lambda_f) ** 2 / float((field.abs() ** 2).sum())
        for flat in top.tolist():
            iy, ix = divmod(flat, s.focal_n)
            yc = (iy - s.focal_n // 2 + off) * s.focal_pitch_m
            xc = (ix - s.focal_n // 2 + off) * s.focal_pitch_m
            e = mft(field, mft_matrix(yc, pupil, s.lambda_f, cdtype), mft_matrix(xc, pupil, s.lambda_f, cdtype))
            irradiance = e.abs() ** 2
            if cell_m is not None:
                irradiance = irradiance * (self.cell_envelope(cell_m, yc)[:, None]
                                           * self.cell_envelope(cell_m, xc)[None, :]).to(irradiance)
            best = max(best, float(irradiance.max()) * scale)
        return best
