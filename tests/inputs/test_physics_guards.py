"""Impossible physics is never answered with a confident number (issue 38 item 5), and the advice of a message is
true for the values at hand (item 6): a measured PSF narrower than diffraction (an LSR above 1, an MTF above the
aperture's) is refused before any work or warned about, naming its pitch, energy and file; a dark frame that clips
more than a small share of the samples warns with the figure; the laser-strength grid always spans the configured
range; a window that holds a tiny share of the light, or an MTF band without a frequency of the window, is said so;
export's advice on a plate too large gives a pitch that works."""
from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch

import codesign.experiments as experiments
from codesign.camera import build_camera
from codesign.config.runtime import command_line_keys
from codesign.data.paramconfig import ParamConfig
from codesign.errors import ConfigError
from codesign.optics import OpticalSystem, OpticsSpec
from codesign.optics.measured import load_measured
from tests.inputs._run import compose_cfg, config_error

CPU = torch.device("cpu")
PITCH = 5.4e-6  # the sensor pitch: the window's
SMOKE = ("+experiment=simulate", "debug=smoke")
ERR = "codesign: configuration error: "


def _cfg(*overrides: str):
    cfg = compose_cfg(*overrides)
    experiments.apply_debug(cfg, command_line_keys(list(overrides)))
    return cfg


def _npy(path, values) -> str:
    np.save(path, values)
    return str(path)


def _delta(tmp_path) -> str:
    d = np.zeros((64, 64))
    d[32, 32] = 1.0
    return _npy(tmp_path / "delta.npy", d)


def _report(caplog, *overrides: str) -> tuple[dict, list[str]]:
    """measured_psf_report of a smoke camera with ``overrides``: (its metrics, its warnings)."""
    from codesign.design.measured_merit import measured_psf_report
    from codesign.experiments.specs import metrics_spec

    cfg = _cfg(*SMOKE, *overrides)
    log = logging.getLogger("codesign.test_physics_guards")
    with caplog.at_level(logging.WARNING, logger="codesign"):
        out = measured_psf_report(build_camera(cfg, CPU), metrics_spec(cfg).mtf_band, log)
    return out, [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


# ---- a measured PSF against the aperture's diffraction limit ------------------------------------------------------
def test_a_measured_delta_is_refused_before_any_work_naming_pitch_energy_and_a_possible_pitch(
        tmp_path, monkeypatch, capsys):
    path = _delta(tmp_path)
    line = config_error(monkeypatch, capsys, tmp_path / "run", *SMOKE, f"optics.psf_file={path}",
                        f"optics.psf_pitch_m={PITCH}")
    assert line == (f"{ERR}optics.psf_file = '{path}': its brightest pixel holds 100% of the light (optics.psf_energy "
                    "= 1), 14.4x the most any mask can put into one pixel of optics.psf_pitch_m = 5.4e-06 m (6.94%: "
                    "the diffraction-limited peak of the 3.83 mm aperture at optics.wavelength_m = 6.33e-07, f = "
                    "0.11 m): a PSF narrower than diffraction (LSR 14.4 > 1) cannot be; possible with "
                    "optics.psf_pitch_m >= 2.05e-05 m or optics.psf_energy <= 0.0694, or a frame of these optics "
                    "without a hot pixel")
    assert not (tmp_path / "run").exists()
    # the advice is true: either value makes the same frame possible
    spec = OpticsSpec.with_samples_across(192, focal_n=160, psf_file=path, psf_pitch_m=PITCH)
    assert load_measured(spec.replace(psf_pitch_m=2.05e-5)).pitch_m == 2.05e-5
    assert load_measured(spec.replace(psf_energy=0.0694)).energy == 0.0694


def test_the_bound_is_the_uncoded_peak_so_the_uncoded_psf_passes_and_the_same_frame_in_smaller_pixels_does_not(
        tmp_path):
    from codesign.optics.measured import diffraction_peak_m2

    spec = OpticsSpec.with_samples_across(192, focal_n=160)
    system = OpticalSystem(spec, dtype=torch.float64)
    # the most light any mask puts into a window pixel, per m^2 x the pixel's area, is h0(0), the LSR's denominator
    assert diffraction_peak_m2(spec) * PITCH**2 == pytest.approx(system.uncoded_peak, rel=1e-12)
    psf0 = system.uncoded_psf().numpy()  # the tightest PSF there is: LSR 1
    path = _npy(tmp_path / "uncoded.npy", psf0)
    energy = float(psf0.sum())
    m = load_measured(spec.replace(psf_file=path, psf_pitch_m=PITCH, psf_energy=energy))
    assert float(m.frame.max()) * m.energy == pytest.approx(system.uncoded_peak, rel=1e-9)
    with pytest.raises(ConfigError, match=r"\(LSR 1\.44 > 1\) cannot be; possible with optics\.psf_pitch_m >= "
                                          r"5\.4e-06 m"):
        load_measured(spec.replace(psf_file=path, psf_pitch_m=PITCH / 1.2, psf_energy=energy))


def test_a_coarse_frame_beyond_diffraction_on_the_window_is_warned_about_and_marked(tmp_path, caplog):
    path = _delta(tmp_path)  # one pixel of 21 um may hold all the light; resampled onto 5.4 um it is too sharp
    out, warnings = _report(caplog, f"optics.psf_file={path}", "optics.psf_pitch_m=2.1e-5")
    assert out["measured_lsr"] > 1 and out["measured_mtf_mean"] > out["diffraction_mtf_mean"]
    assert out["measured_psf_physical"] is False
    assert warnings == [
        f"measured PSF {path}: on the 160 x 160 window of 5.4e-06 m its LSR {out['measured_lsr']:.3g} > 1 and "
        f"mtf_mean {out['measured_mtf_mean']:.4f} > {out['diffraction_mtf_mean']:.4f}, the diffraction limit (the "
        "uncoded aperture's): no mask can do this, so these figures are not the optics': the frame is narrower than "
        "diffraction at optics.psf_pitch_m = 2.1e-05 m (check the file's pixel pitch at the sensor plane, "
        "optics.psf_energy = 1 and the file; the frame is coarser than the window and was interpolated)"]


def test_a_dark_frame_that_clips_many_samples_warns_with_the_count_and_the_light_it_added(tmp_path, caplog):
    rows, cols = np.mgrid[:64, :64]
    disk = (rows - 48) ** 2 + (cols - 32) ** 2 <= 8**2  # a spot wider than diffraction, clear of rows 0..30
    frame = 100.0 + disk * (99200.0 / disk.sum())  # 99,200 counts of light on a background of 100
    dark = np.full((64, 64), 100.0)
    dark[:31] = 100.5  # 31 rows of 64: 1,984 samples below the dark frame by 0.5, i.e. 992 counts = 1 % of the light
    f, d = _npy(tmp_path / "psf.npy", frame), _npy(tmp_path / "dark.npy", dark)
    out, warnings = _report(caplog, f"optics.psf_file={f}", f"optics.psf_pitch_m={PITCH}", f"optics.psf_dark_file={d}")
    assert out["measured_psf_clipped_samples"] == 1984
    assert out["measured_psf_clipped_light"] == pytest.approx(0.01, rel=1e-12)
    assert out["measured_psf_physical"] is True
    assert warnings == [
        f"optics.psf_dark_file '{d}': 1,984 of the 4,096 samples of optics.psf_file '{f}' (48.4%) lie below it and "
        "were clipped to 0, which added 1% to the frame's light (a dark frame of the same exposure and gain leaves "
        "about half of an empty background's samples below it: its noise; a brighter one clips the PSF's own light)"]


def test_a_frame_whose_light_misses_the_window_is_refused(tmp_path, caplog):
    frame = np.zeros((400, 400))
    frame[5:25, 5:25] = 1.0  # 175 px from the frame's centre, the axis with psf_centre=frame: beyond the window
    path = _npy(tmp_path / "corner.npy", frame)
    with pytest.raises(ConfigError) as err:
        _report(caplog, f"optics.psf_file={path}", f"optics.psf_pitch_m={PITCH}", "optics.psf_centre=frame")
    assert str(err.value) == (f"optics.psf_file = '{path}': none of its light falls on the 160 x 160 optics window "
                              "(0.000864 m, shifted by (0, 0) px of optics.psf_pitch_m = 5.4e-06 m onto the axis "
                              "(frame centre)): check optics.psf_pitch_m, optics.psf_centre and the file")


def test_a_psf_energy_that_underflows_is_refused(tmp_path, monkeypatch, capsys):
    frame = np.ones((16, 16))
    path = _npy(tmp_path / "flat.npy", frame)
    line = config_error(monkeypatch, capsys, tmp_path / "run", *SMOKE, f"optics.psf_file={path}",
                        f"optics.psf_pitch_m={PITCH}", "optics.psf_energy=1e-300")
    assert line == (f"{ERR}optics.psf_energy = 1e-300: a frame holding less than 1e-06 of the light through the "
                    "aperture is not its PSF (its samples would underflow the float32 simulation to 0): must be >= "
                    "1e-06 and <= 1")


# ---- the laser-strength grid spans the configured range -----------------------------------------------------------
def test_one_laser_strength_level_for_a_range_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    line = config_error(monkeypatch, capsys, tmp_path / "run", "+experiment=baseline", "debug=smoke",
                        "data.params.alpha_l_levels=1")
    assert line == (f"{ERR}data.params.alpha_l_levels = 1: cannot span data.params.alpha_l_range = [0, 2e+06]: must "
                    "be >= 2 (both ends are levels), or give a range of one strength [a, a]")
    from codesign.data.params import laser_strength_levels  # the advice holds: one strength, one level

    one = ParamConfig.from_config({"alpha_l_range": [5, 5], "alpha_l_levels": 1})
    assert laser_strength_levels(one).tolist() == [5.0]
    assert laser_strength_levels(ParamConfig.from_config({"alpha_l_levels": 2})).tolist() == [0.0, 2e6]


@pytest.mark.parametrize("params, levels", [
    ({"alpha_l_levels": 2, "alpha_l_spacing": "log"}, [0.0, 2e6]),          # was {0, 1}
    ({"alpha_l_levels": 3, "alpha_l_spacing": "log"}, [0.0, 1.0, 2e6]),
    ({"alpha_l_range": [0.5, 500], "alpha_l_levels": 4, "alpha_l_spacing": "log"}, [0.5, 5.0, 50.0, 500.0]),  # 1..
])
def test_the_laser_strength_grid_holds_both_ends_of_the_range(params, levels):
    from codesign.data.params import laser_strength_levels

    grid = laser_strength_levels(ParamConfig.from_config(params)).tolist()
    assert grid == pytest.approx(levels, rel=1e-12)
    assert grid[0] == levels[0] and grid[-1] == levels[-1]  # the ends exactly


def test_a_laser_strength_range_beyond_float32_is_refused():
    with pytest.raises(ConfigError) as err:
        ParamConfig.from_config({"alpha_l_range": [0, 1e40]})
    assert str(err.value) == "data.params.alpha_l_range = 1e+40: must be a finite number >= 0 and <= 1e+12"
    assert float(torch.tensor(1e40, dtype=torch.float32)) == math.inf  # what it would have trained on


# ---- a window that holds a sliver of the light; a band without frequencies ---------------------------------------
def test_a_window_holding_a_tiny_share_of_the_light_warns_with_the_share(caplog):
    from omegaconf import OmegaConf

    from codesign.design.check import sampling_report
    from codesign.optics import build_mask

    cfg = _cfg("+experiment=psf", "debug=smoke", "optics.wavelength_m=1e-5")  # the mask's rings lie far outside
    spec = OpticsSpec.from_config(OmegaConf.to_container(cfg.optics, resolve=True))
    system = OpticalSystem(spec)
    mask = build_mask(OmegaConf.to_container(cfg.mask, resolve=True), system.grid, spec.aperture_diameter_m)
    log = logging.getLogger("codesign.test_physics_guards")
    with caplog.at_level(logging.WARNING, logger="codesign"):
        out = sampling_report(mask, spec, (0.0, 0.5), log, "halfring mask")
    energy = out["phase_sampling"]["window_energy"]
    assert energy == pytest.approx(float(system.mask_psf(mask).detach().sum()), rel=1e-5) and energy < 1e-3
    warnings = [r.getMessage() for r in caplog.records if "optics window holds" in r.getMessage()]
    assert warnings == [
        f"halfring mask: the 160 x 160 optics window holds {100 * energy:.2g}% of its PSF's light (under 1%): its LSR "
        "and MTF describe that part only, the rest falls beyond the window (metrics.json: phase_sampling.window_energy"
        "); widen the window (optics.focal_n) or check the optics the mask was designed for (optics.wavelength_m, "
        "optics.focal_length_m, optics.aperture_diameter_m)"]


SAME_WAVELENGTH = ("sensor.wavelength_background_m=1e-4", "sensor.wavelength_laser_m=1e-4")


@pytest.mark.parametrize("experiment, extra", [("psf", ()), ("mask_search", SAME_WAVELENGTH),
                                               ("joint", SAME_WAVELENGTH), ("export", SAME_WAVELENGTH),
                                               ("tolerance", ())])
def test_a_window_narrower_than_the_band_needs_is_refused_before_any_work(experiment, extra, tmp_path, monkeypatch,
                                                                          capsys):
    line = config_error(monkeypatch, capsys, tmp_path / "run", f"+experiment={experiment}", "debug=smoke",
                        "optics.wavelength_m=1e-4", *extra)  # was "IndexError: amin(): Expected reduction dim -1 ..."
    assert line == (f"{ERR}metrics.mtf_band = [0.0, 0.5]: holds no frequency of the 160 x 160 optics window: its "
                    "0.000864 m are 0.301 lambda f / W_a (lambda f / W_a = 0.00287 m), so its first frequency above 0 "
                    "is 3.32 of the cutoff W_a / (lambda f); needs optics.focal_n >= 1064, or the optics the window "
                    "was meant for (optics.wavelength_m = 0.0001, optics.focal_length_m = 0.11, "
                    "optics.aperture_diameter_m = 0.00383)")
    from codesign.optics.metrics import require_band_frequencies

    require_band_frequencies(OpticsSpec(wavelength_m=1e-4, pupil_pitch_m=2e-5, focal_n=1064), (0.0, 0.5))  # true


# ---- the simulate settings: angles that reach the lens, a sensor that is not blind --------------------------------
@pytest.mark.parametrize("typed, message", [
    ("simulate.laser_angle_rad=[2,0]", "simulate.laser_angle_rad[0] = 2: must be a finite number >= -1.5708 and <= "
                                       "1.5708"),
    ("simulate.params.exposure_s=0", "simulate.params.exposure_s = 0: must be a finite number > 0"),
])
def test_simulate_settings_no_sensor_can_see_are_refused(typed, message, tmp_path, monkeypatch, capsys):
    line = config_error(monkeypatch, capsys, tmp_path / "run", *SMOKE, typed)
    assert line == ERR + message


def test_a_laser_beyond_the_sensor_is_said_to_miss_it(caplog):
    from codesign.experiments.simulate import warn_laser_off_sensor

    with caplog.at_level(logging.WARNING, logger="codesign"):
        assert warn_laser_off_sensor([0.06, 0.0], 0.11, 13.7e-3, halo=True) is False  # 6.6 mm: on the sensor
        assert warn_laser_off_sensor([0.2, 0.0], 0.11, 13.7e-3, halo=False) is True   # f * 0.2 = 22 mm
    assert [r.getMessage() for r in caplog.records] == [
        "simulate.laser_angle_rad = [0.2, 0]: the laser's spot lands (22, 0) mm from the sensor's centre, beyond the "
        "sensor (13.7 mm square): nothing of the laser reaches the captures (sensor.laser_halo is off)"]


# ---- export: the advice on a plate too large works ----------------------------------------------------------------
def test_a_plate_too_large_names_the_size_and_a_pitch_that_works(tmp_path, monkeypatch, capsys):
    from codesign.fab.surface import ExportSpec

    line = config_error(monkeypatch, capsys, tmp_path / "run", "+experiment=export", "debug=smoke",
                        "export.size_m=0.5")
    # was "export.pitch_m = 8e-06: ... raise export.pitch_m to >= 4.86e-07 m", which 8e-06 already is
    assert line == (f"{ERR}export.size_m = 0.5: gives a plate of 62500 x 62500 pixels at export.pitch_m = 8e-06 m; at "
                    "most 8192 per side: raise export.pitch_m to >= 6.11e-05 m or lower export.size_m to <= 0.06553 m")
    optics = OpticsSpec()
    assert ExportSpec(size_m=0.5, pitch_m=6.11e-5).plate_n(optics) <= 8192
    assert ExportSpec(size_m=0.06553, pitch_m=8e-6).plate_n(optics) <= 8192
    with pytest.raises(ConfigError) as err:  # null size: the aperture's support sets it; only the pitch can change
        ExportSpec(pitch_m=1e-7).plate_n(optics)
    assert str(err.value) == ("export.pitch_m = 1e-07: gives a plate of 39798 x 39798 pixels (the aperture's support, "
                              "0.00398 m); at most 8192 per side: raise export.pitch_m to >= 4.86e-07 m")
    assert ExportSpec(pitch_m=4.86e-7).plate_n(optics) <= 8192
