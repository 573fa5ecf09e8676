"""The mask at other laser lines (codesign.optics.lines): the phase a surface made for one wavelength gives at
another, the LSR per line, and the settings that ask for them.

References: the blazed grating's diffraction efficiencies (a 2 pi m-wrapped linear phase seen with the scale s puts
sinc^2(m s - k) of the light into its order k, so its brightest spot reads max_k sinc^2(m s - k) of the uncoded
peak), a plain tilt (unwrapped: the whole Airy spot moves, LSR 1 at every line), and the index's closed form."""
from __future__ import annotations

import math

import pytest
import torch

from codesign.errors import ConfigError
from codesign.optics import OpticalSystem, OpticsSpec, metrics
from codesign.optics.lines import LaserLines, curve_wavelengths, phase_scale, smooth_lsr, surface_phase, worst
from codesign.optics.materials import Material

SCALE = 1.2  # the line 633 nm / 1.2 = 527.5 nm in a material of constant index: the phase is 1.2x the design's
PERIODS = 8  # grating periods across the aperture: its orders lie 8 lambda f / W_a apart


@pytest.fixture(scope="module")
def system():
    spec = OpticsSpec.with_samples_across(160, focal_n=160, laser_wavelengths_m=[633e-9 / SCALE, 633e-9])
    return OpticalSystem(spec, dtype=torch.float64)


def _grating(system) -> torch.Tensor:
    g = system.grid
    return (2 * math.pi * PERIODS / system.spec.aperture_diameter_m * g.u[None, :]).expand(g.n, g.n)


def _sinc2(x: float) -> float:
    return 1.0 if x == 0 else (math.sin(math.pi * x) / (math.pi * x)) ** 2


def test_phase_scale_closed_forms():
    assert phase_scale(lambda lam: 1.5, 633e-9, 633e-9 / SCALE) == pytest.approx(SCALE, rel=1e-15)
    silica = Material()
    n0, n1 = silica.index(633e-9), silica.index(532e-9)
    assert phase_scale(silica.index, 633e-9, 532e-9) == pytest.approx((n1 - 1) * 633 / ((n0 - 1) * 532), rel=1e-15)
    assert n1 == pytest.approx(1.46071, abs=2e-5)  # Malitson's fit (conf/material/fused_silica.yaml)


@pytest.mark.parametrize("wrap, expected", [
    (None, 1.0),  # a continuous ramp is a tilt at every line: the whole spot moves
    (1, max(_sinc2(SCALE - k) for k in range(-2, 4))),  # 0.8751: order 1 keeps sinc^2(0.2)
    (2, max(_sinc2(2 * SCALE - k) for k in range(-2, 6))),  # 0.5728: order 2 of the 2-wave plate, sinc^2(0.4)
])
def test_wrapped_grating_efficiency(system, wrap, expected):
    lines = LaserLines(system, lambda lam: 1.5)
    lines.wrap = wrap
    rows = lines.table(_grating(system))
    assert [r["wavelength_m"] for r in rows] == [633e-9 / SCALE, 633e-9]
    assert rows[1]["lsr"] == pytest.approx(1.0, abs=2e-6)  # the design line: a tilt, whatever the wrap
    # 8 periods across a super-Gaussian aperture: the orders' peaks are the infinite grating's within ~3 %
    assert rows[0]["lsr"] == pytest.approx(expected, rel=0.005 if wrap != 2 else 0.03)
    if wrap is not None:
        assert worst(rows) is rows[1]


def test_surface_phase_wraps_at_whole_waves():
    phase = torch.linspace(-20, 20, 401, dtype=torch.float64)
    for m in (1, 3):
        w = surface_phase(phase, m)
        assert float(w.min()) >= 0 and float(w.max()) < 2 * math.pi * m
        steps = (w - phase) / (2 * math.pi * m)
        assert torch.allclose(steps, steps.round(), atol=1e-12)
    assert surface_phase(phase, None) is phase


def test_design_line_is_the_design_phase(system):
    """At the design wavelength the wrapped phase changes nothing: the same continuous peak, to the last bit."""
    phase = 17.0 * (system.grid.rho / (system.spec.aperture_diameter_m / 2)) ** 2
    lines = LaserLines(system, Material().index)
    assert lines.design_index == 1 and lines.systems[1] is system
    row = lines.table(phase)[1]
    assert row["lsr"] == system.continuous_peak(phase).value / system.uncoded_peak


def test_smooth_worst_case_bounds_every_line(system):
    phase = (11.0 * (system.grid.rho / (system.spec.aperture_diameter_m / 2)) ** 2).requires_grad_(True)
    lines = LaserLines(system, Material().index)
    smooth, sampled = smooth_lsr(system, phase, None, 16.0, 2, lines=lines)
    per_line = [float(s.psf(lines.phase(phase, i)).max()) / s.uncoded_peak for i, s in enumerate(lines.systems)]
    assert float(sampled) >= max(per_line) * (1 - 1e-12)  # the half-sample grid can only add samples
    assert float(smooth) >= float(sampled)
    smooth.backward()
    assert phase.grad is not None and torch.isfinite(phase.grad).all() and phase.grad.abs().sum() > 0


def test_one_smooth_lsr_over_samples_sub_grids_and_lines(system):
    """smooth_lsr: the samples alone without a phase, the half-sample grids with one, the worst line with lines;
    the sampled LSR is the samples' maximum over h0(0) in each case."""
    phase = 11.0 * (system.grid.rho / (system.spec.aperture_diameter_m / 2)) ** 2
    psf, h0 = system.psf(phase), system.uncoded_peak
    smooth, sampled = smooth_lsr(system, None, psf, 16.0, 2)
    assert float(smooth) == float(metrics.lsr_smooth(psf, h0, 16.0)) and float(sampled) == float(psf.max()) / h0
    samples = system.lsr_samples(phase, psf, 2)
    smooth, sampled = smooth_lsr(system, phase, None, 16.0, 2)
    assert float(smooth) == float(metrics.lsr_smooth(samples, h0, 16.0)) and float(sampled) == float(samples.max()) / h0
    lines = LaserLines(system, Material().index)
    ratios = lines.ratio_samples(phase, 2)
    smooth, sampled = smooth_lsr(system, phase, psf, 16.0, 2, lines=lines)
    assert float(smooth) == float(metrics.lsr_smooth(ratios, 1.0, 16.0)) and float(sampled) == float(ratios.max())


def test_line_settings_are_checked():
    with pytest.raises(ConfigError) as err:
        OpticsSpec(focal_n=1280, laser_wavelengths_m=[405e-9])
    assert str(err.value) == (
        "optics.laser_wavelengths_m[0] = 4.05e-07: at this line the sampled pupil's spectrum repeats every lambda f "
        "/ pupil_pitch = 0.004467 m, less than the 0.006912 m window: its PSF would alias; need "
        "optics.pupil_pitch_m <= 6.445e-06 m, a smaller optics.focal_n, or a longer line")
    with pytest.raises(ConfigError, match=r"laser_wavelengths_m = 5e-07: must be null \(the design wavelength alone\)"):
        OpticsSpec(laser_wavelengths_m=5e-7)
    with pytest.raises(ConfigError, match="names a line twice"):
        OpticsSpec(laser_wavelengths_m=[5.32e-7, 5.32e-7])
    with pytest.raises(ConfigError, match=r"optics.wrap_waves = 0"):
        OpticsSpec(wrap_waves=0)
    assert OpticsSpec().laser_lines == (633e-9,)


def test_curve_leaves_out_the_aliased_lines():
    kept, dropped = curve_wavelengths(OpticsSpec(focal_n=1280, pupil_pitch_m=7.48e-6))
    assert min(kept) == pytest.approx(4.75e-7) and 1.064e-6 in kept and 6.33e-7 in kept
    assert dropped == (4e-7, 4.05e-7, 4.25e-7, 4.5e-7)  # below 469 nm the 6.9 mm window aliases at 7.48 um
