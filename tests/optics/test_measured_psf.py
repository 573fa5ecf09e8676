"""A measured PSF in place of the computed one (optics.psf_file, codesign/optics/measured.py): the loader's physics
(unit energy, whole-pixel registration, energy-conserving resampling against a binned Gaussian, an exact copy at
the sensor pitch), a measured PSF equal to the computed one reproducing the computed pipeline, every bad file
refused before any work with its exact message, and the four experiments that take one (simulate, baseline with
fine-tuning from a checkpoint trained on the computed PSF, evaluate, restore) at smoke size; the others refuse it."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image
from scipy.special import erf

import codesign.experiments as experiments
from codesign.camera import build_camera
from codesign.config.runtime import command_line_keys
from codesign.errors import ConfigError
from codesign.experiments.specs import with_measured_psf
from codesign.optics import OpticsSpec
from codesign.optics.measured import centroid_px, integrate_axis, load_measured, resample
from codesign.train.checkpoint import save_checkpoint
from codesign.experiments.resume import check_resume_config, load_initial_weights
from codesign.train.model_setup import build_model
from codesign.train.optim import init_weights
from tests.inputs._run import compose_cfg, config_error

CPU = torch.device("cpu")
PITCH = 5.4e-6
SMALL = ("data.image_size=48", "data.padded_size=64")  # smoke optics, a 48 px network image: seconds per run
ALLOWED = "a measured PSF is a 16-bit PNG / TIFF frame or a .npy array of floats"


def _spec(tmp_path, values: np.ndarray, name: str = "psf.npy", **kw) -> OpticsSpec:
    path = tmp_path / name
    np.save(path, values)
    return OpticsSpec.with_samples_across(64, focal_n=64, psf_file=str(path), **{"psf_pitch_m": PITCH, **kw})


def _png(path, arr) -> str:
    Image.fromarray(arr).save(path)
    return str(path)


def _binned_gaussian(n: int, pitch: float, sigma: float, centre=(0.0, 0.0)) -> np.ndarray:
    """Exact integrals of a unit 2-D Gaussian over n x n pixels of ``pitch`` centred on the axis (sample n // 2)."""
    edges = (np.arange(n + 1) - n // 2 - 0.5) * pitch
    g = [np.diff(0.5 * erf((edges - c) / (np.sqrt(2) * sigma))) for c in centre]
    return np.outer(g[0], g[1])


def _cfg(*overrides: str):
    cfg = compose_cfg(*overrides)
    experiments.apply_debug(cfg, command_line_keys(list(overrides)))
    return cfg


# ---- (1) the loader's physics ------------------------------------------------------------------------------------
def test_unit_energy_and_centring_by_whole_pixels(tmp_path):
    frame = np.zeros((41, 37))
    frame[20 + 7 - 1: 20 + 7 + 2, 18 - 5 - 1: 18 - 5 + 2] = [[1, 2, 1], [2, 6, 2], [1, 2.5, 1]]  # off by (7, -5) px
    frame *= 123.0  # any scale: normalized to unit energy
    # psf_energy 0.2: a frame that held all the light in 3 x 3 px would be narrower than diffraction (refused)
    m = load_measured(_spec(tmp_path, frame, psf_centre="centroid", psf_energy=0.2))
    assert m.frame.sum() == pytest.approx(1.0, abs=1e-15)
    placed = m.place(OpticsSpec.with_samples_across(64, focal_n=64))
    assert placed.shift == (-7, 5) and placed.outside == pytest.approx(0.0, abs=1e-15)
    assert placed.psf.sum() == pytest.approx(0.2, abs=1e-14)
    cy, cx = centroid_px(placed.psf)
    assert abs(cy) <= 0.5 and abs(cx) <= 0.5  # the centroid on the axis, to the nearest whole pixel
    # a whole-pixel shift at the window's pitch: the samples themselves, none interpolated
    np.testing.assert_array_equal(placed.psf[31:34, 31:34], frame[26:29, 12:15] / frame.sum() * 0.2)
    # psf_energy: the share of all the light the frame holds; frame = the file's centre pixel on the axis
    m = load_measured(_spec(tmp_path, frame, psf_energy=0.125, psf_centre="frame"))
    placed = m.place(OpticsSpec.with_samples_across(64, focal_n=64))
    assert placed.shift == (0, 0) and placed.psf.sum() == pytest.approx(0.125, abs=1e-15)


def test_design_centring_puts_the_centroid_where_the_design_psfs_is(tmp_path):
    spec = OpticsSpec.with_samples_across(64, focal_n=64)
    design = np.zeros((64, 64))
    design[32 + 9, 32 - 4] = 1.0  # a design PSF 9 px below and 4 px left of the axis
    frame = np.zeros((21, 21))
    frame[10, 10] = 1.0  # the measured spot in the frame's centre: where the axis lies is not known
    # psf_energy 0.01: one pixel holding all the light would be narrower than diffraction (refused)
    placed = load_measured(_spec(tmp_path, frame, psf_energy=0.01)).place(spec, design)
    assert placed.shift == (9, -4) and placed.psf[41, 28] == 0.01
    # at half the window's pitch: the same place in metres, 18 and -8 file pixels
    placed = load_measured(_spec(tmp_path, frame, psf_pitch_m=PITCH / 2, psf_energy=0.01)).place(spec, design)
    assert placed.shift == (18, -8) and placed.psf.sum() == pytest.approx(0.01, abs=1e-14)
    assert np.unravel_index(placed.psf.argmax(), placed.psf.shape) == (41, 28)


@pytest.mark.parametrize("pitch_in", [2.7e-6, 2.0e-6])
def test_resampling_conserves_energy_and_matches_the_binned_gaussian(pitch_in):
    sigma = 8e-6  # 1.5 sensor pixels: a sharp PSF, where resampling errs most
    n_in = int(round(400e-6 / pitch_in))
    frame = _binned_gaussian(n_in, pitch_in, sigma)  # what a sensor of pitch_in would integrate
    out = resample(frame / frame.sum(), pitch_in, (0, 0), 64, PITCH)
    ref = _binned_gaussian(64, PITCH, sigma)  # the same Gaussian integrated over the 5.4 um window pixels
    assert out.sum() == pytest.approx(1.0, abs=1e-12) and out.min() >= 0
    err = np.abs(out - ref).max() / ref.max()
    assert err < {2.7e-6: 5e-4, 2.0e-6: 2e-3}[pitch_in], err  # measured 2.4e-4 and 1.4e-3
    # a window smaller than the frame loses exactly the light beyond it
    small = resample(frame / frame.sum(), pitch_in, (0, 0), 4, PITCH)
    assert small.sum() == pytest.approx(_binned_gaussian(4, PITCH, sigma).sum(), rel=1e-3)
    # which resample computes from the rows and columns that can reach the window: as from the whole frame
    start = [(s - n // 2) * pitch_in for s, n in zip((3, -2), frame.shape)]
    whole = integrate_axis(integrate_axis(frame, pitch_in, start[0], 4, PITCH, 0), pitch_in, start[1], 4, PITCH, 1)
    np.testing.assert_allclose(resample(frame, pitch_in, (3, -2), 4, PITCH), whole, rtol=1e-12, atol=1e-15)


def test_at_the_sensor_pitch_the_frame_is_copied_cropped_or_padded_exactly():
    rng = np.random.default_rng(0)
    frame = rng.random((7, 9))
    out = resample(frame, PITCH * (1 + 5e-10), (0, 0), 16, PITCH)  # within 1e-9: a copy, no interpolation
    np.testing.assert_array_equal(out[8 - 3: 8 + 4, 8 - 4: 8 + 5], frame)
    assert (out != 0).sum() == frame.size
    big = rng.random((40, 40))
    np.testing.assert_array_equal(resample(big, PITCH, (0, 0), 16, PITCH), big[20 - 8: 20 + 8, 20 - 8: 20 + 8])
    np.testing.assert_array_equal(resample(big, PITCH, (3, -2), 16, PITCH), big[17 - 8: 17 + 8, 22 - 8: 22 + 8])


def test_the_dark_frame_is_subtracted_and_what_falls_below_it_clipped(tmp_path):
    frame = np.full((9, 9), 100, np.uint16)
    frame[4, 4], frame[0, 0] = 1100, 97  # 1000 counts of light; one sample 3 counts below the dark level
    dark = np.full((9, 9), 100, np.uint16)
    spec = OpticsSpec.with_samples_across(64, focal_n=64, psf_file=_png(tmp_path / "f.png", frame), psf_energy=0.05,
                                          psf_pitch_m=PITCH, psf_dark_file=_png(tmp_path / "d.png", dark))
    m = load_measured(spec)
    assert m.clipped == 1 and m.frame[4, 4] == 1.0 and m.frame.sum() == 1.0 and m.kind == "16-bit"
    import tifffile  # TIFF frames read as PNG ones

    tifffile.imwrite(tmp_path / "f.tif", frame)
    tifffile.imwrite(tmp_path / "d.tiff", dark)
    m2 = load_measured(spec.replace(psf_file=str(tmp_path / "f.tif"), psf_dark_file=str(tmp_path / "d.tiff")))
    np.testing.assert_array_equal(m2.frame, m.frame)


# ---- (2) a measured PSF equal to the computed one reproduces the computed pipeline --------------------------------
@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The smoke-size computed window PSF saved as a measured file would hold it (psf.npy, at the sensor pitch, with
    its window energy), and a "lab" frame of it: blurred, at 2.7 um, shifted, 16-bit counts on a dark level."""
    from scipy.ndimage import gaussian_filter

    d = tmp_path_factory.mktemp("measured")
    cam = build_camera(_cfg("+experiment=simulate", "debug=smoke"), CPU)
    psf = cam.frozen_optics().state.psf.numpy()
    np.save(d / "psf.npy", psf)
    lab = np.roll(gaussian_filter(np.kron(psf.astype(np.float64), np.ones((2, 2))), 1.5), (7, -5), (0, 1))
    noise = np.random.default_rng(0).normal(0, 3, lab.shape)
    _png(d / "lab.png", np.rint(lab / lab.max() * 50000 + 100 + noise).astype(np.uint16))
    _png(d / "dark.png", np.full(lab.shape, 100, np.uint16))
    return {"dir": d, "psf": str(d / "psf.npy"), "energy": repr(float(psf.astype(np.float64).sum())),
            "lab": ["optics.psf_file=" + str(d / "lab.png"), "optics.psf_pitch_m=2.7e-6",
                    "optics.psf_dark_file=" + str(d / "dark.png")]}


def _equal(files):
    return [f"optics.psf_file={files['psf']}", f"optics.psf_pitch_m={PITCH}", f"optics.psf_energy={files['energy']}"]


def test_the_computed_psf_as_a_measured_file_gives_the_same_psf_kernel_otf_and_images(files):
    computed = build_camera(_cfg("+experiment=simulate", "debug=smoke"), CPU)
    measured = build_camera(_cfg("+experiment=simulate", "debug=smoke", *_equal(files)), CPU)
    a, b = computed.frozen_optics(), measured.frozen_optics()
    assert measured.placement.shift == (0, 0)
    for name in ("kernel", "otf"):  # the sensor kernel and the Wiener stage's OTF
        torch.testing.assert_close(getattr(b, name), getattr(a, name), rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(b.state.psf, a.state.psf, rtol=1e-6, atol=1e-12)
    from codesign.data.params import fixed_scene_params

    scenes = torch.rand(2, 1, computed.scene_size, computed.scene_size, generator=torch.Generator().manual_seed(0))
    params = fixed_scene_params(2, alpha_l=1e6, laser_angle_rad=[0.008, -0.012], alpha_b=0.7, c1=0.2, c2=1.0)
    out_a, out_b = computed(scenes, params, seed=3), measured(scenes, params, seed=3)
    assert out_a["saturated"].any()
    for name in ("sensor_dn", "irradiance", "laser"):
        torch.testing.assert_close(out_b[name], out_a[name], rtol=1e-6, atol=1e-6 * float(out_a[name].max()))
    assert measured.halo_on is False


def _run(tmp_path, name, *overrides, monkeypatch=None) -> dict:
    """Run an experiment in this process (as `python -m codesign ...` does) and return its metrics.json."""
    run_dir = tmp_path / name
    monkeypatch.setattr(experiments, "explicit_keys", lambda: command_line_keys(list(overrides)))
    threads = f"threads={torch.get_num_threads()}"  # tests/conftest.py: CODESIGN_TEST_THREADS on a shared machine
    experiments.run_experiment(compose_cfg(*overrides, threads), run_dir=run_dir)
    return json.loads((run_dir / "metrics.json").read_text())


def test_simulate_with_the_computed_psf_as_a_measured_file_writes_the_computed_runs_outputs(files, tmp_path,
                                                                                            monkeypatch):
    a = _run(tmp_path, "computed", "+experiment=simulate", "debug=smoke", monkeypatch=monkeypatch)
    b = _run(tmp_path, "measured", "+experiment=simulate", "debug=smoke", *_equal(files), monkeypatch=monkeypatch)
    for key in ("saturated_fraction_alpha_l_1e6", "laser_peak_alpha_l_1e6", "lsr_sampled", "window_energy",
                "bsr_window"):
        assert b[key] == pytest.approx(a[key], rel=1e-6), key
    assert b["measured_lsr"] == pytest.approx(b["design_lsr"], rel=1e-6) == a["lsr_sampled"]
    assert b["measured_mtf_mean"] == pytest.approx(b["design_mtf_mean"], rel=1e-6)
    assert b["measured_psf_shift_px"] == [0, 0] and b["laser_halo"] is False
    for name in ("example_sensor.npy", "example_irradiance_target.npy"):
        x, y = np.load(tmp_path / "computed" / name), np.load(tmp_path / "measured" / name)
        np.testing.assert_allclose(y, x, rtol=1e-6, atol=1e-6 * np.abs(x).max())
    for png in sorted((tmp_path / "computed" / "captures").glob("*.png")):
        x = np.asarray(Image.open(png), dtype=np.int64)
        y = np.asarray(Image.open(tmp_path / "measured" / "captures" / png.name), dtype=np.int64)
        assert np.abs(x - y).max() <= 1, png.name  # 16-bit counts: a rounding tie at most
    assert (tmp_path / "measured" / "measured_psf.png").is_file()
    assert not (tmp_path / "computed" / "measured_psf.png").exists()


# ---- (3) every bad input: its exact message, before any work ------------------------------------------------------
def _bad_files(d):
    """name -> (optics overrides, key, message after "key = 'path': ")."""
    rgb = _png(d / "rgb.png", np.zeros((8, 8, 3), np.uint8))
    g8 = _png(d / "g8.png", np.full((8, 8), 10, np.uint8))
    zero = _png(d / "zero.png", np.zeros((8, 8), np.uint16))
    sat = np.full((8, 8), 100, np.uint16)
    sat[3:5, 4] = 65535
    sat = _png(d / "sat.png", sat)
    ok = np.full((8, 8), 100, np.uint16)
    ok[4, 4] = 5000
    ok = _png(d / "ok.png", ok)
    small_dark = _png(d / "dark6.png", np.full((6, 8), 100, np.uint16))
    np.save(d / "nan.npy", np.where(np.eye(8) > 0, np.nan, 1.0))
    np.save(d / "inf.npy", np.full((8, 8), np.inf))
    neg = np.ones((8, 8))
    neg[0, 0] = -0.01
    np.save(d / "neg.npy", neg)
    np.save(d / "cube.npy", np.ones((2, 8, 8)))
    np.save(d / "tiny.npy", np.ones((2, 2)))
    np.save(d / "complex.npy", np.ones((8, 8), np.complex128))
    np.save(d / "ones.npy", np.ones((8, 8)))
    (d / "bad.npy").write_bytes(b"not an array")
    (d / "psf.jpg").write_bytes(b"x")
    f, k, p = "optics.psf_file", "optics.psf_dark_file", "optics.psf_pitch_m"
    return {
        "8-bit": ([g8], f, "has uint8 samples: expected 16-bit sensor counts (8-bit files cannot hold the sensor's "
                           f"range); {ALLOWED}"),
        "rgb": ([rgb], f, f"PNG mode RGB: expected a single-channel 16-bit image (mode I;16); {ALLOWED}"),
        "all-zero": ([zero], f, "holds no light: every sample is 0"),
        "zero-after-dark": ([ok, f"{k}={ok}"], f, f"holds no light: every sample is 0 after subtracting "
                                                  f"optics.psf_dark_file '{ok}' (is it the frame itself?)"),
        "saturated": ([sat], f, "has 2 sample(s) at 65535 (the 16-bit maximum): the PSF's peak is clipped, so its "
                                "shape and LSR would be wrong: take a shorter exposure"),
        "nan": ([str(d / "nan.npy")], f, "has 8 non-finite sample(s) (NaN or inf): a PSF holds finite energies only"),
        "inf": ([str(d / "inf.npy")], f, "has 64 non-finite sample(s) (NaN or inf): a PSF holds finite energies "
                                         "only"),
        "negative": ([str(d / "neg.npy")], f, "has negative samples down to -0.01 (0.01 of its peak): light is never "
                                              "negative (rounding down to 1e-06 of the peak is clipped to 0); save the "
                                              "frame before its background was subtracted and give the background as "
                                              "optics.psf_dark_file"),
        "not-2d": ([str(d / "cube.npy")], f, "has shape (2, 8, 8): expected one 2-D frame (H, W)"),
        "too-small": ([str(d / "tiny.npy")], f, "is 2 x 2 px: a PSF frame must be at least 3 x 3 px"),
        "complex": ([str(d / "complex.npy")], f, "holds complex128 values: expected real numbers (float or integer "
                                                 "samples)"),
        "unreadable": ([str(d / "bad.npy")], f, "cannot be read as a .npy array (ValueError: "),
        "suffix": ([str(d / "psf.jpg")], f, f"must be a .png, .tif, .tiff, .npy file: {ALLOWED}"),
        "missing": ([str(d / "nowhere.npy")], f, "no such file"),
        "dark-shape": ([ok, f"{k}={small_dark}"], k, f"is 8 x 6 px, optics.psf_file '{ok}' 8 x 8 px: the dark frame "
                                                     "must be taken with the same camera settings and size"),
        "dark-kind": ([str(d / "ones.npy"), f"{k}={ok}"], k, f"is a 16-bit file, optics.psf_file "
                                                             f"'{d / 'ones.npy'}' a .npy one: the dark frame must be "
                                                             "of the same kind and units"),
        "pitch-missing": ([ok, f"{p}=null"], p, None),
    }


BAD = ("8-bit", "rgb", "all-zero", "zero-after-dark", "saturated", "nan", "inf", "negative", "not-2d", "too-small",
       "complex", "unreadable", "suffix", "missing", "dark-shape", "dark-kind", "pitch-missing")


def _bad(d, name):
    files, key, message = _bad_files(d)[name]
    overrides = {"psf_file": files[0], "psf_pitch_m": PITCH}
    for extra in files[1:]:
        k, v = extra.split("=", 1)
        overrides[k.split(".")[1]] = None if v == "null" else v
    if message is None:  # the OpticsSpec's own
        value = "None"
        message = ("pitch missing: the pixel pitch of optics.psf_file at the sensor plane in m is needed to resample "
                   "it onto the optics window, e.g. optics.psf_pitch_m=5.4e-06 for a frame taken with the sensor "
                   "itself")
    else:
        value = repr(overrides["psf_dark_file"] if key.endswith("dark_file") else files[0])
    return overrides, key, value, message


@pytest.mark.parametrize("name", BAD)
def test_every_bad_file_is_refused_naming_key_file_and_what_is_allowed(tmp_path, name):
    overrides, key, value, message = _bad(tmp_path, name)
    with pytest.raises(ConfigError, match="^" + re.escape(f"{key} = {value}: {message}")):
        load_measured(OpticsSpec(**overrides))


@pytest.mark.parametrize("overrides,message", [
    ({"psf_dark_file": "d.png"}, "optics.psf_dark_file = 'd.png': describes optics.psf_file, which is null: give the "
                                 "measured PSF with optics.psf_file=PATH, or leave optics.psf_dark_file null"),
    ({"psf_pitch_m": PITCH}, "optics.psf_pitch_m = 5.4e-06: describes optics.psf_file, which is null: give the "
                             "measured PSF with optics.psf_file=PATH, or leave optics.psf_pitch_m null"),
    ({"psf_file": "p.npy", "psf_pitch_m": -1.0}, "optics.psf_pitch_m = -1.0: must be a finite number > 0 and <= "
                                                 "0.01"),
    ({"psf_file": 5, "psf_pitch_m": PITCH}, "optics.psf_file = 5: must be null or the path of a file (a measured PSF "
                                            "is a 16-bit PNG / TIFF frame or a .npy array of floats)"),
    ({"psf_energy": 1.5}, "optics.psf_energy = 1.5: must be a finite number > 0 and <= 1"),
    ({"psf_centre": "middle"}, "optics.psf_centre = 'middle': must be one of design, centroid, frame"),
])
def test_bad_measured_psf_values(overrides, message):
    with pytest.raises(ConfigError, match="^" + re.escape(message) + "$"):
        OpticsSpec(**overrides)


@pytest.mark.parametrize("experiment", ["simulate", "baseline", "evaluate", "restore"])
@pytest.mark.parametrize("name", ["saturated", "8-bit", "pitch-missing", "dark-shape"])
def test_a_bad_file_stops_every_experiment_before_any_work(experiment, name, monkeypatch, capsys, tmp_path):
    overrides, key, value, message = _bad(tmp_path, name)
    typed = [f"optics.{k}={'null' if v is None else v}" for k, v in overrides.items()]
    line = config_error(monkeypatch, capsys, tmp_path / "run", f"+experiment={experiment}", "debug=smoke", *typed)
    assert line == f"codesign: configuration error: {key} = {value}: {message}"
    assert not (tmp_path / "run").exists()


def test_a_pitch_without_a_file_stops_the_run_before_any_work(monkeypatch, capsys, tmp_path):
    line = config_error(monkeypatch, capsys, tmp_path / "run", "+experiment=simulate", "debug=smoke",
                        "optics.psf_pitch_m=5.4e-6")
    assert line == ("codesign: configuration error: optics.psf_pitch_m = 5.4e-06: describes optics.psf_file, which is "
                    "null: give the measured PSF with optics.psf_file=PATH, or leave optics.psf_pitch_m null")


@pytest.mark.parametrize("experiment", ["psf", "mask_search", "joint"])
def test_the_other_experiments_refuse_a_measured_psf(experiment, files, monkeypatch, capsys, tmp_path):
    line = config_error(monkeypatch, capsys, tmp_path / "run", f"+experiment={experiment}", "debug=smoke",
                        *_equal(files))
    assert line == (f"codesign: configuration error: optics.psf_file = '{files['psf']}': +experiment={experiment} "
                    "computes the PSF of its mask and takes no measured one (a measured PSF replaces the computed one "
                    "in baseline, evaluate, restore, simulate): leave it null")


def test_only_the_four_experiments_take_a_measured_psf():
    takers = {n for n in experiments.EXPERIMENTS if experiments.protocol(n).measured_psf}
    assert takers == {"simulate", "baseline", "evaluate", "restore"}


def test_a_measured_psf_keeps_the_mask_frozen(files):
    cam = build_camera(_cfg("+experiment=simulate", "debug=smoke", *_equal(files)), CPU)
    with pytest.raises(ConfigError, match="a measured PSF fixes the optics: the mask cannot be trained through it"):
        cam.set_trainable(True)


# ---- (4) the four experiments, and checkpoints from before the measured PSF ----------------------------------------
@pytest.fixture(scope="module")
def computed_checkpoint(tmp_path_factory):
    """A checkpoint of a network trained on the computed PSF, written before the optics.psf_* keys existed."""
    cfg = _cfg("+experiment=baseline", "debug=smoke", *SMALL)
    torch.manual_seed(0)
    model = build_model(cfg)
    init_weights(model)
    config = OmegaConf.to_container(cfg, resolve=True)
    for key in ("psf_file", "psf_pitch_m", "psf_dark_file", "psf_energy", "psf_centre"):
        config["optics"].pop(key)
    path = tmp_path_factory.mktemp("ckpt") / "checkpoint.pt"
    save_checkpoint(path, {"model": model.state_dict(), "step": 4, "config": config})
    return path, config


def test_an_older_checkpoint_resumes_and_fine_tunes_on_a_measured_psf(computed_checkpoint, files):
    path, saved = computed_checkpoint
    check_resume_config(saved, _cfg("+experiment=baseline", "debug=smoke", *SMALL), "trainer.resume")
    with pytest.raises(ConfigError, match="was trained with different optics"):  # another PSF is another physics
        check_resume_config(saved, _cfg("+experiment=baseline", "debug=smoke", *SMALL, *files["lab"]),
                            "trainer.resume")
    cfg = _cfg("+experiment=baseline", "debug=smoke", *SMALL, *files["lab"])
    assert load_initial_weights(build_model(cfg), path, cfg)["init_steps"] == 4


def test_a_checkpoints_measured_psf_is_kept_unless_this_run_names_one():
    ckpt = OmegaConf.create({"optics": {"focal_n": 160, "psf_file": "/lab/a.png", "psf_pitch_m": 2.7e-6}})
    run = OmegaConf.create({"optics": {"psf_file": None, "psf_pitch_m": None}})
    assert with_measured_psf(ckpt, run).optics.psf_file == "/lab/a.png"
    back = with_measured_psf(ckpt, run, frozenset({"optics.psf_file"}))  # optics.psf_file=null typed
    assert back.optics.psf_file is None and back.optics.psf_pitch_m is None and back.optics.focal_n == 160
    other = with_measured_psf(ckpt, OmegaConf.create({"optics": {"psf_file": "/lab/b.npy", "psf_pitch_m": 5e-6}}))
    assert (other.optics.psf_file, other.optics.psf_pitch_m, other.optics.psf_energy) == ("/lab/b.npy", 5e-6, 1.0)


def _reports_measured_and_design(m: dict, path: str) -> None:
    assert m["measured_psf"] == path and m["laser_halo"] is False
    assert m["measured_psf_shift_px"] == [-7, 4] and m["measured_psf_pitch_m"] == 2.7e-6
    assert 0 < m["design_lsr"] < m["measured_lsr"] < 1  # unit energy in its frame, against 0.148 in the window
    assert 0 < m["measured_mtf_mean"] < m["design_mtf_mean"] < 1  # blurred
    assert 0.99 < m["measured_psf_window_energy"] <= 1.0 and 0 < m["measured_psf_outside_window"] < 0.01


def test_fine_tuning_evaluating_and_restoring_on_a_measured_psf(computed_checkpoint, files, tmp_path, monkeypatch):
    ckpt, _ = computed_checkpoint
    lab = str(files["dir"] / "lab.png")
    # fine-tuning the network of the computed PSF on the measured one: the documented command
    m = _run(tmp_path, "fine", "+experiment=baseline", "debug=smoke", *SMALL, f"init.checkpoint={ckpt}",
             *files["lab"], monkeypatch=monkeypatch)
    _reports_measured_and_design(m, lab)
    assert m["init_checkpoint"] == str(ckpt) and m["init_steps"] == 4 and m["steps"] == 4
    fine = torch.load(tmp_path / "fine" / "checkpoint.pt", weights_only=True)["config"]["optics"]
    assert fine["psf_file"] == lab and fine["psf_dark_file"] == str(files["dir"] / "dark.png")
    # evaluating the computed PSF's network on the measured PSF
    m = _run(tmp_path, "eval", "+experiment=evaluate", "debug=smoke", f"checkpoint={ckpt}", *files["lab"],
             monkeypatch=monkeypatch)
    _reports_measured_and_design(m, lab)
    assert set(m["evaluation"]) == {"laser_0", "laser_1e6", "H1"}
    # restoring a capture with it (the Wiener stage's OTF is the measured PSF's)
    capture = _png(tmp_path / "capture.png", np.random.default_rng(1).integers(200, 5000, (48, 48)).astype(np.uint16))
    m = _run(tmp_path, "restore", "+experiment=restore", f"input={capture}", f"checkpoint={ckpt}", *files["lab"],
             monkeypatch=monkeypatch)
    _reports_measured_and_design(m, lab)
    assert (tmp_path / "restore" / "restored_capture.png").is_file()
