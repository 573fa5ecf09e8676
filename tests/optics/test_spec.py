"""OpticsSpec validation: every bad value raises ConfigError naming the key and what is allowed."""
from __future__ import annotations

import math

import pytest
import torch

from codesign.errors import ConfigError
from codesign.optics import OpticalSystem, OpticsSpec

W_A = 3.83e-3
LAMBDA_F = 633e-9 * 0.11
PAPER = {"pupil_pitch_m": 3.74e-6}  # Table 1 (optics=paper): a 1068-sample pupil grid


def test_defaults_are_table1_at_the_converged_sampling():
    s = OpticsSpec()
    assert s.wavelength_m == 633e-9
    assert s.focal_length_m == 0.11
    assert s.aperture_diameter_m == 3.83e-3
    # the pupil at 384 samples across W_a, the converged sampling (docs/optics.md); Table 1's 3.74 um is optics=paper
    assert s.pupil_pitch_m == 9.974e-6
    assert s.focal_pitch_m == 5.4e-6
    assert s.focal_n == 640
    assert s.supergaussian_order == 50.0


def test_derived_quantities():
    s = OpticsSpec()
    assert s.lambda_f == pytest.approx(LAMBDA_F, rel=1e-15)
    assert s.lambda_f_over_d == pytest.approx(LAMBDA_F / W_A, rel=1e-15)
    assert s.samples_per_lambda_f_over_d == pytest.approx(LAMBDA_F / W_A / 5.4e-6, rel=1e-15)
    assert s.cutoff_frequency == pytest.approx(W_A / LAMBDA_F, rel=1e-15)
    assert s.replica_period_m == pytest.approx(LAMBDA_F / 9.974e-6, rel=1e-15)
    assert s.focal_extent_m == pytest.approx(640 * 5.4e-6, rel=1e-15)
    # the super-Gaussian is 1e-20 at the support radius
    a = math.exp(-((2 * s.aperture_support_radius_m / W_A) ** 2) ** s.supergaussian_order)
    assert a == pytest.approx(1e-20, rel=1e-9)
    # the automatic grid is even and holds the support diameter
    assert s.grid_n == s.min_pupil_n
    assert s.grid_n % 2 == 0
    assert s.grid_n * s.pupil_pitch_m >= 2 * s.aperture_support_radius_m


def test_with_samples_across_sets_pitch():
    s = OpticsSpec.with_samples_across(64, focal_n=64)
    assert s.pupil_pitch_m == pytest.approx(W_A / 64, rel=1e-15)
    assert s.samples_across_aperture == pytest.approx(64, rel=1e-12)
    assert s.focal_n == 64
    s2 = OpticsSpec.with_samples_across(50, aperture_diameter_m=2e-3, focal_n=32)
    assert s2.pupil_pitch_m == pytest.approx(2e-3 / 50, rel=1e-15)


@pytest.mark.parametrize("value", [-1.0, 0.0, -3.74e-6, float("nan"), float("inf"), "1e-5", None, True])
def test_bad_pupil_pitch_is_rejected(value):
    with pytest.raises(ConfigError, match=r"^optics\.pupil_pitch_m = .*: must be a finite number > 0$") as info:
        OpticsSpec(pupil_pitch_m=value)
    assert info.value.key == "optics.pupil_pitch_m"


@pytest.mark.parametrize("key,value,fragment", [
    ("wavelength_m", 1.0, r"optics\.wavelength_m = 1\.0: must be a finite number >= 1e-08 and <= 0\.0001"),
    ("wavelength_m", 0.0, r"optics\.wavelength_m = 0\.0: must be a finite number >= 1e-08"),
    ("focal_length_m", 0.0, r"optics\.focal_length_m = 0\.0: must be a finite number > 0 and <= 100"),
    ("aperture_diameter_m", -1e-3, r"optics\.aperture_diameter_m = -0\.001: must be a finite number > 0"),
    ("supergaussian_order", 0.5, r"optics\.supergaussian_order = 0\.5: must be a finite number >= 1 and <= 1000"),
    ("focal_pitch_m", 0.0, r"optics\.focal_pitch_m = 0\.0: must be a finite number > 0"),
    ("focal_n", 7, r"optics\.focal_n = 7: must be an integer >= 8 and <= 16384"),
    ("focal_n", 64.5, r"optics\.focal_n = 64\.5: must be an integer >= 8 and <= 16384"),
    ("focal_n", 20000, r"optics\.focal_n = 20000: must be an integer >= 8 and <= 16384"),
])
def test_out_of_range_numbers_name_key_and_range(key, value, fragment):
    with pytest.raises(ConfigError, match=fragment) as info:
        OpticsSpec(**{key: value})
    assert info.value.key == f"optics.{key}"
    assert info.value.value == value


def test_pupil_n_too_small_names_key_and_minimum():
    need = OpticsSpec(**PAPER).min_pupil_n
    assert need == 1068
    with pytest.raises(ConfigError, match=rf"optics\.pupil_n = 10: .*cannot hold the aperture.*must be >= {need}, "
                                          r"or null for automatic"):
        OpticsSpec(**PAPER, pupil_n=10)
    with pytest.raises(ConfigError, match=rf"optics\.pupil_n = {need - 2}: .*must be >= {need}"):
        OpticsSpec(**PAPER, pupil_n=need - 2)
    assert OpticsSpec(**PAPER, pupil_n=need).grid_n == need
    assert OpticsSpec(**PAPER, pupil_n=need + 100).grid_n == need + 100


def test_pupil_n_not_integer():
    with pytest.raises(ConfigError, match=r"optics\.pupil_n = 1100\.5: must be an integer >= 2"):
        OpticsSpec(**PAPER, pupil_n=1100.5)


def test_fft_n_smaller_than_grid():
    with pytest.raises(ConfigError, match=r"optics\.fft_n = 100: must be >= the pupil grid size 1068"):
        OpticsSpec(**PAPER, fft_n=100)


def test_aliasing_focal_pitch_names_focal_pitch():
    limit = LAMBDA_F / (2 * W_A)
    with pytest.raises(ConfigError, match=r"optics\.focal_pitch_m = .*would alias the intensity PSF: 1\.82 samples "
                                          r"per lambda\*f/W_a, need >= 2, i\.e\. focal_pitch_m <= 9\.09e-06 m"):
        OpticsSpec(focal_pitch_m=1e-5, focal_n=64)
    with pytest.raises(ConfigError, match=r"^optics\.focal_pitch_m"):
        OpticsSpec(focal_pitch_m=limit * (1 + 1e-9), focal_n=64)
    s = OpticsSpec(focal_pitch_m=limit, focal_n=64)  # exactly Nyquist is allowed
    assert s.samples_per_lambda_f_over_d == pytest.approx(2.0, rel=1e-12)


def test_window_wider_than_replica_period_names_pupil_pitch():
    # 16 samples across: replica period lambda f / pitch = 0.291 mm < 64 x 5.4 um = 0.3456 mm
    with pytest.raises(ConfigError, match=r"^optics\.pupil_pitch_m = 0\.000239375: the focal window "
                                          r"\(64 x 5\.4e-06 m = 0\.0003456 m\) is wider than the period "
                                          r"lambda\*f/pupil_pitch = 0\.0002909 m.*need pupil_pitch_m <= "
                                          r"0\.0002015 m or a smaller focal_n"):
        OpticsSpec.with_samples_across(16, focal_n=64)
    # the same pitch with a window narrower than the period is fine
    s = OpticsSpec.with_samples_across(16, focal_n=48)
    assert s.focal_extent_m <= s.replica_period_m


@pytest.mark.parametrize("name", ["bogus", "MFT", "", None, "direct"])
def test_bad_propagator_name(name):
    with pytest.raises(ConfigError, match=r"optics\.propagator = .*: must be one of auto, mft, czt, fft"):
        OpticsSpec(propagator=name)


def test_from_config_unknown_key():
    with pytest.raises(ConfigError, match=r"^optics\.focal_lenght_m = 0\.1: unknown key; allowed: aperture_diameter_m, "
                                          r"fft_n, focal_length_m, focal_n, focal_pitch_m, laser_wavelengths_m, "
                                          r"propagator, psf_centre, psf_dark_file, psf_energy, psf_file, psf_pitch_m, "
                                          r"pupil_n, pupil_pitch_m, scene_spectrum, supergaussian_order, "
                                          r"wavelength_m, wrap_waves$"):
        OpticsSpec.from_config({"focal_lenght_m": 0.1, "wavelength_m": 633e-9})


def test_from_config_prefix_is_used_in_messages():
    with pytest.raises(ConfigError, match=r"^sensor\.optics\.pupil_pitch_m = -1"):
        OpticsSpec.from_config({"pupil_pitch_m": -1}, prefix="sensor.optics")
    with pytest.raises(ConfigError, match=r"^other\.prefix = 1: unknown key"):
        OpticsSpec.from_config({"prefix": 1}, prefix="other")


def test_from_config_roundtrip():
    cfg = {"wavelength_m": 633e-9, "focal_length_m": 0.11, "aperture_diameter_m": 3.83e-3,
           "supergaussian_order": 50, "pupil_pitch_m": 9.974e-6, "pupil_n": None, "focal_pitch_m": 5.4e-6,
           "focal_n": 640, "propagator": "auto", "fft_n": None}
    s = OpticsSpec.from_config(cfg)
    assert s == OpticsSpec(**cfg)


def test_replace_revalidates():
    s = OpticsSpec.with_samples_across(64, focal_n=64)
    assert s.replace(focal_n=32).focal_n == 32
    with pytest.raises(ConfigError, match=r"optics\.focal_pitch_m"):
        s.replace(focal_pitch_m=2e-5)


def test_spec_is_frozen():
    s = OpticsSpec()
    with pytest.raises(Exception):
        s.focal_n = 10  # type: ignore[misc]


@pytest.mark.parametrize("method", ["mft", "fft"])
def test_integer_valued_float_sizes_give_a_working_system(method):
    # require_number(integer=True) accepts 64.0 (e.g. a YAML value written as 64.0 or 6.4e1); the spec is then
    # valid, so the system built from it must work like focal_n=64.
    s = OpticsSpec.with_samples_across(64, focal_n=64.0)
    ref = OpticsSpec.with_samples_across(64, focal_n=64)
    system = OpticalSystem(s, dtype=torch.float64, method=method)
    psf = system.uncoded_psf()
    assert psf.shape == (64, 64)
    expected = OpticalSystem(ref, dtype=torch.float64, method=method).uncoded_psf()
    torch.testing.assert_close(psf, expected)
    peak = system.continuous_peak(torch.zeros_like(system.grid.aperture)).value
    assert peak / system.uncoded_peak == pytest.approx(1.0, abs=1e-6)
