"""The tolerance model's physics: no error is the plate as exported, a detuning of nothing is the ideal design,
defocus against the closed-form Strehl ratio, a doubled binary plate is flat, a common level error is a piston,
a rotated grating keeps its LSR; and the error draws are reproducible."""
from __future__ import annotations

import math

import pytest
import torch

from codesign.design.merit import evaluate_mask
from codesign.optics.materials import Material
from codesign.fab.surface import Plate, PlatePhase
from codesign.fab.tolerance import Errors, PlateEvaluator, ToleranceSpec, draw
from codesign.optics import OpticalSystem, OpticsSpec

BAND = (0.0, 0.5)
SILICA = Material()  # the fused-silica default


@pytest.fixture(scope="module")
def system():
    return OpticalSystem(OpticsSpec.with_samples_across(96, focal_n=128), dtype=torch.float64)


def _evaluator(system, phase, levels=None, seed=0):
    plate = Plate.from_phase(phase, system.grid, system.spec.wavelength_m, SILICA.index(system.spec.wavelength_m),
                             levels, 1)
    return plate, PlateEvaluator(plate, system, SILICA, BAND, torch.Generator().manual_seed(seed), batch=4)


def _design_phase(system):
    g = system.grid
    return 9.0 * torch.sin(3 * g.angle) * (g.rho / 1.9e-3) ** 2 + 30 * (g.rho / 1.9e-3) ** 3


def test_no_error_is_the_exported_plate_and_zero_detuning_the_ideal(system):
    phase = _design_phase(system)
    _, ev = _evaluator(system, phase)
    ideal, _ = evaluate_mask(system, PlatePhase(phase), BAND, 16.0)
    e = Errors.zeros(2, None)
    e.wavelength[1] = 1e-18  # through a system rebuilt at lambda + 1e-18 m and the index there
    lsr, mtf = ev(e)
    assert float(lsr[0]) == pytest.approx(ideal["lsr_sampled"], rel=1e-12)
    assert float(mtf[0]) == pytest.approx(ideal["mtf_mean"], rel=1e-12)
    assert float(lsr[1]) == pytest.approx(ideal["lsr_sampled"], rel=1e-9)
    assert float(mtf[1]) == pytest.approx(ideal["mtf_mean"], rel=1e-9)


def test_defocus_matches_the_closed_form_strehl_ratio(system):
    """A flat plate with the sensor dz off focus: W20 = dz W_a^2 / (8 f^2); on-axis irradiance over the focused
    one = sinc^2(W20 / lambda) for a uniform circular pupil (the super-Gaussian edge: 0.5 % at a quarter wave, 2 % at
    half a wave), and exactly |sum A exp(i phi)|^2 / (sum A)^2 on the grid."""
    s = system.spec
    _, ev = _evaluator(system, torch.zeros_like(system.grid.rho))
    e = Errors.zeros(2, None)
    for i, waves in enumerate((0.25, 0.5)):
        e.dz[i] = waves * s.wavelength_m * 8 * s.focal_length_m**2 / s.aperture_diameter_m**2
    lsr, _ = ev(e)
    a = system.grid.aperture
    for i, (waves, tol) in enumerate(((0.25, 5e-3), (0.5, 2.5e-2))):
        # exact on this grid: the peak is on the axis, E(0) = sum A exp(i phi) over E0(0) = sum A
        rho2 = system.grid.rho**2 / (s.aperture_diameter_m / 2) ** 2
        on_axis = (a * torch.exp(2j * math.pi * waves * rho2)).sum().abs() ** 2 / a.sum() ** 2
        assert float(lsr[i]) == pytest.approx(float(on_axis), rel=1e-9)
        strehl = (math.sin(math.pi * waves) / (math.pi * waves)) ** 2  # 0.8106, 0.4053
        assert float(lsr[i]) == pytest.approx(strehl, rel=tol)


def test_doubled_binary_plate_is_flat_and_a_common_level_error_is_a_piston(system):
    g = system.grid
    phase = 2 * math.pi * (g.u[None, :] / g.pitch + 0.5).expand(g.n, g.n) / 6
    plate, ev = _evaluator(system, phase, levels=2)
    e = Errors.zeros(3, 2)
    e.depth[1] = 1.0  # heights x 2: phase 0 / 2 pi, a flat plate: the uncoded peak
    e.level[2] = 37e-9  # every level 37 nm higher: a piston
    lsr, mtf = ev(e)
    assert float(lsr[1]) == pytest.approx(1.0, rel=1e-9)
    assert float(lsr[2]) == pytest.approx(float(lsr[0]), rel=1e-9)
    assert float(mtf[2]) == pytest.approx(float(mtf[0]), rel=1e-9)
    assert float(lsr[0]) < 0.5


def test_mirrored_shifts_and_a_quarter_turn_keep_the_lsr(system):
    """A plate symmetric under u -> -u and u <-> v, shifted by +dx, -dx or +dy, gives the same LSR (mirror
    images, transposes); a grating turned by 90 degrees is the grating along v (a transposed PSF)."""
    g = system.grid
    bowl = 25 * (g.rho / 1.9e-3) ** 2 + 4 * torch.cos(4 * g.angle)
    _, ev = _evaluator(system, bowl, levels=8)
    e = Errors.zeros(3, 8)
    e.dx[0], e.dx[1], e.dy[2] = 1.5 * g.pitch, -1.5 * g.pitch, 1.5 * g.pitch
    lsr, mtf = ev(e)
    assert float(lsr[1]) == pytest.approx(float(lsr[0]), rel=1e-9)
    assert float(lsr[2]) == pytest.approx(float(lsr[0]), rel=1e-9)
    assert float(mtf[2]) == pytest.approx(float(mtf[0]), rel=1e-9)
    grating = (2 * math.pi * (g.u[None, :] / g.pitch + 0.5) / 6).expand(g.n, g.n)
    _, ev = _evaluator(system, grating, levels=4)
    e = Errors.zeros(2, 4)
    e.rotation[1] = math.pi / 2
    lsr, _ = ev(e)
    assert float(lsr[1]) == pytest.approx(float(lsr[0]), rel=1e-9)


def test_draws_are_reproducible_and_only_touch_their_source():
    spec = ToleranceSpec()
    a = draw(spec, ("shift",), 5, 4, torch.Generator().manual_seed(3))
    b = draw(spec, ("shift",), 5, 4, torch.Generator().manual_seed(3))
    assert torch.equal(a.dx, b.dx) and torch.equal(a.dy, b.dy) and bool((a.dx != 0).all())
    assert not a.depth.any() and not a.level.any() and not a.wavelength.any() and not a.dz.any()
    c = draw(spec, ("level_noise",), 5, None, torch.Generator().manual_seed(3))
    assert c.level is None and torch.equal(c.roughness, torch.full((5,), spec.level_noise_m, dtype=torch.float64))


def test_tolerance_spec_refuses_bad_values():
    from codesign.errors import ConfigError

    with pytest.raises(ConfigError, match=r"tolerance.samples = 0: must be an integer >= 1"):
        ToleranceSpec(samples=0)
    with pytest.raises(ConfigError, match=r"tolerance.shift_m = -1e-05: must be a finite number >= 0"):
        ToleranceSpec(shift_m=-1e-5)
    with pytest.raises(ConfigError, match=r"tolerance.lsr_ceiling = 'published': must be auto or a number > 0"):
        ToleranceSpec(lsr_ceiling="published")
