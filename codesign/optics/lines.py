"""The mask at every laser line: its surface, made for the design wavelength, seen by a laser at another one.

A mask is made for the design wavelength lambda0 in a material of index n(lambda): the design phase phi0, wrapped
at 2 pi m (``optics.wrap_waves`` = m: m = 1 the usual diffractive plate, m > 1 a multi-order plate; None the
continuous surface, not wrapped), becomes the height h = wrap(phi0) lambda0 / (2 pi (n(lambda0) - 1)). A laser at
lambda sees the phase

    phi(lambda) = 2 pi (n(lambda) - 1) h / lambda = s(lambda) wrap(phi0),
    s(lambda) = (n(lambda) - 1) lambda0 / ((n(lambda0) - 1) lambda)

At lambda0, s = 1 and the wrapped phase equals phi0 modulo 2 pi (the same PSF); elsewhere the wrap's steps are
s 2 pi m, no longer whole waves, and the light they fail to steer returns to a diffraction-limited zero order.
Every line has its own optical system (the same pupil grid and focal window, its own lambda f): its PSF, its
uncoded peak h0(0) (LSR = the coded peak over the uncoded one at the same line) and its continuous peak.

The saturated area at a line: the window pixels where a laser of strength alpha_l (its uncoded peak irradiance
over the saturation irradiance, as in the sensor model) saturates the sensor, psf > h0(0) / alpha_l.
"""
from __future__ import annotations

import math
from typing import Callable

import torch

from codesign.optics import metrics
from codesign.optics.psf import OpticalSystem
from codesign.optics.spec import OpticsSpec

TWO_PI = 2 * math.pi
SATURATION_ALPHA_L = 1e6  # the laser strength of the saturated area: the strongest of the evaluation's alpha_l
# the common laser lines a dazzle camera meets (nm): violet and blue diodes, green diodes and DPSS, HeNe, Nd:YAG
COMMON_LINES_M = (405e-9, 450e-9, 520e-9, 532e-9, 633e-9, 1064e-9)
CURVE_RANGE_M = (400e-9, 1100e-9)  # the range of the LSR-against-wavelength plots


def curve_wavelengths(spec: OpticsSpec, points: int = 29, extra: tuple = ()) -> tuple[tuple, tuple]:
    """(wavelengths of an LSR-against-wavelength curve, those of the range left out): ``points`` evenly over
    CURVE_RANGE_M, the common lines, the spec's lines and ``extra``, without those whose PSF the window or the
    pupil grid would alias (OpticsSpec's line checks)."""
    lo, hi = CURVE_RANGE_M
    grid = [lo + (hi - lo) * k / (points - 1) for k in range(points)]
    every = sorted({round(w, 15) for w in (*grid, *COMMON_LINES_M, *spec.laser_lines, *extra)})
    kept, dropped = [], []
    for w in every:
        (kept if spec.line_problem(w) is None else dropped).append(w)
    return tuple(kept), tuple(dropped)


def phase_scale(index: Callable[[float], float], design_m: float, line_m: float) -> float:
    """s(lambda): the phase a surface made for ``design_m`` gives at ``line_m``, per radian of design phase."""
    return (index(line_m) - 1) * design_m / ((index(design_m) - 1) * line_m)


def surface_phase(phase: torch.Tensor, wrap_waves: int | None) -> torch.Tensor:
    """The design phase as the surface holds it: modulo 2 pi ``wrap_waves`` (in [0, 2 pi m)), or as it is (None).
    Differentiable: the remainder's derivative is 1 away from the wrap's steps."""
    if wrap_waves is None:
        return phase
    period = TWO_PI * wrap_waves
    w = torch.remainder(phase, period)
    return torch.where(w >= period, w - period, w)  # remainder can round up to exactly the period


class LaserLines:
    """The optical systems of a spec's laser lines (``spec.laser_lines``) and the mask's phase at each.

    Args:
        system: the design wavelength's OpticalSystem (reused for a line at that wavelength);
        index: the material's refractive index n(lambda) (``Material.index``); lines: override of
            ``system.spec.laser_lines`` (e.g. a curve of wavelengths for a plot).
    """

    def __init__(self, system: OpticalSystem, index: Callable[[float], float], lines: tuple | None = None):
        spec: OpticsSpec = system.spec
        self.spec, self.index, self.wrap = spec, index, spec.wrap_waves
        self.wavelengths = tuple(float(w) for w in (lines if lines is not None else spec.laser_lines))
        self.scales = [phase_scale(index, spec.wavelength_m, w) for w in self.wavelengths]
        self.systems = [system if spec.is_design_wavelength(w) else
                        OpticalSystem(spec.replace(wavelength_m=w, laser_wavelengths_m=None, scene_spectrum=None),
                                      dtype=system.dtype,
                                      device=system.grid.rho.device)
                        for w in self.wavelengths]
        # the line at the design wavelength, if any: its phase is the design phase, its PSF the design PSF
        self.design_index = next((i for i, sy in enumerate(self.systems) if sy is system), None)

    def __len__(self) -> int:
        return len(self.wavelengths)

    def phase(self, phase: torch.Tensor, i: int) -> torch.Tensor:
        """The phase line ``i`` sees of the surface made from the design ``phase``."""
        if i == self.design_index:
            return phase  # the wrap changes nothing at the design wavelength
        return surface_phase(phase, self.wrap) * self.scales[i]

    def ratio_samples(self, phase: torch.Tensor, grids: int, cell_m: float | None = None,
                      design_psf: torch.Tensor | None = None) -> torch.Tensor:
        """Every line's smooth-LSR samples (``OpticalSystem.lsr_samples``) over its own uncoded peak, stacked
        along the rows, float64: their max is the worst line's sampled LSR and their p-norm a smooth worst case.
        ``design_psf``: the design wavelength's window PSF when already computed."""
        out = []
        for i, system in enumerate(self.systems):
            ph = self.phase(phase, i)
            psf = design_psf if design_psf is not None and i == self.design_index else system.psf(ph, cell_m)
            out.append(system.lsr_samples(ph, psf, grids, cell_m).to(torch.float64) / system.uncoded_peak)
        return torch.cat(out, dim=-2)

    @torch.no_grad()
    def table(self, phase: torch.Tensor, cell_m: float | None = None, alpha_l: float = SATURATION_ALPHA_L,
              rel_tol: float = 3e-3) -> list[dict]:
        """Per line: wavelength, phase scale, the certified continuous LSR, the sampled LSR, the window energy and
        the saturated area [window pixels] at ``alpha_l``."""
        return self.table_of_phases([self.phase(phase, i) for i in range(len(self))], cell_m, alpha_l, rel_tol)

    @torch.no_grad()
    def table_of_phases(self, phases: list[torch.Tensor], cell_m: float | None = None,
                        alpha_l: float = SATURATION_ALPHA_L, rel_tol: float = 3e-3) -> list[dict]:
        """``table`` of the phases each line sees, given (e.g. an exported plate's, quantized heights included)."""
        rows = []
        for i, (system, ph) in enumerate(zip(self.systems, phases)):
            psf = system.psf(ph, cell_m).to(torch.float64)
            peak = system.continuous_peak(ph, cell_m, rel_tol)
            rows.append({"wavelength_m": system.spec.wavelength_m, "phase_scale": self.scales[i],
                         "lsr": peak.value / system.uncoded_peak, "lsr_bound": peak.bound / system.uncoded_peak,
                         "lsr_sampled": float(psf.max()) / system.uncoded_peak,
                         "window_energy": float(psf.sum()),
                         "saturated_px": int((psf * alpha_l > system.uncoded_peak).sum())})
        return rows


def smooth_lsr(system: OpticalSystem, phase: torch.Tensor | None, psf: torch.Tensor | None, p: float, grids: int = 1,
               cell_m: float | None = None, lines: LaserLines | None = None, dtype: torch.dtype | None = None
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """The smooth LSR ||h||_p / h0(0) of a mask, and its sampled LSR max(h) / h0(0) without gradient: the one
    function the mask search, the joint training's constraint and the figures of merit take it from.

    Taken over the window's samples of ``psf`` (m, m) and, given the ``phase`` (n, n) [rad] it came from, the focal
    grids offset by half a sample (``grids``: 1, 2 or 4; ``OpticalSystem.lsr_samples``); with ``lines`` (a
    LaserLines), over every line's samples, each over its own uncoded peak, in float64: the smooth worst case over
    the lines (``psf``, when given, is the design wavelength's). ``phase`` None: ``psf``'s samples alone (no
    sub-grids, no lines). ``psf`` None: computed from ``phase``. ``cell_m``: the mask's plate cell [m]
    (``OpticalSystem.psf``); ``dtype``: the samples cast to it first (None: as computed). Both values are
    dimensionless tensors, (...) for a psf (..., m, m).
    """
    if lines is not None and phase is not None:
        r = lines.ratio_samples(phase, grids, cell_m, psf)
        return metrics.lsr_smooth(r, 1.0, p), r.detach().max()
    if phase is None:
        samples = psf
    else:
        samples = system.lsr_samples(phase, system.psf(phase, cell_m) if psf is None else psf, grids, cell_m)
    if dtype is not None:
        samples = samples.to(dtype)
    h0 = system.uncoded_peak
    return metrics.lsr_smooth(samples, h0, p), metrics.lsr_sampled(samples.detach(), h0)


def worst(rows: list[dict]) -> dict:
    """The row of the highest LSR."""
    return max(rows, key=lambda r: r["lsr"])
