"""Bad config values, as typed on the command line: each stops the run before any work (exit 2) with one line
naming the key, the value and what is allowed. One row per message; the spec-level messages of every key are
also tested next to their specs (tests/optics/test_spec.py, tests/sensor/test_sensor_spec.py, ...)."""
from __future__ import annotations

import re

import pytest

from codesign.experiments import EXPERIMENTS, root_keys
from codesign.optics.masks import families
from tests.cli import run_codesign
from tests.inputs._run import compose_cfg, config_error

MTF_BAND = "must be [low, high] with 0 <= low < high <= 1 (frequency normalized to the incoherent cutoff"

ROWS = [
    # ---- ring lists, masks (psf) --------------------------------------------------------------------------
    ("psf", "mask.preset=null mask.r=5 mask.theta=1",
     "mask.r = 5: must be a list of ring radii (units of lambda f / W_a)"),
    ("psf", "mask.preset=null mask.r=[1,abc] mask.theta=[1,2]", "mask.r[1] = 'abc': must be a finite number"),
    ("psf", "mask.preset=null mask.r=[13.6,91.8] mask.theta=[1.86]",
     "mask.theta = [1.86]: must have the same length as mask.r (2 values) and at least one value"),
    ("psf", "mask.m_range=5", "mask.m_range = 5: must be [m_min, m_max]"),
    ("psf", "mask.r_bounds=5", "mask.r_bounds = 5: must be [lo, hi] with 0 < lo < hi"),
    ("psf", "mask=freeform mask.n_terms=abc", "mask.n_terms = 'abc': must be an integer >= 1 and <= 1000"),
    ("psf", "mask=freeform mask.init_convention=xyz", "mask.init_convention = 'xyz': must be one of atan, atan2"),
    ("psf", "metrics.mtf_band=0.5", f"metrics.mtf_band = 0.5: {MTF_BAND}, beyond which the MTF is 0)"),
    ("psf", "metrics.lsr_p=0.5", "metrics.lsr_p = 0.5: must be a finite number >= 1 and <= 1024"),
    # ---- optics: NaN / inf / wrong type / negative size / consistency -----------------------------------------
    ("psf", "optics.focal_n=nan", "optics.focal_n = nan: must be an integer >= 8 and <= 16384"),
    ("psf", "optics.aperture_diameter_m=inf",
     "optics.aperture_diameter_m = inf: must be a finite number > 0 and <= 10"),
    ("psf", "optics.pupil_pitch_m=abc", "optics.pupil_pitch_m = 'abc': must be a finite number > 0"),
    ("psf", "optics.focal_n=-640", "optics.focal_n = -640: must be an integer >= 8 and <= 16384"),
    ("psf", "optics.pupil_n=100",  # the pupil grid holds the aperture
     "optics.pupil_n = 100: the pupil grid (100 x 2e-05 m) cannot hold the aperture (W_a = 0.00383 m with its "
     "super-Gaussian edge): must be >= 202, or null for automatic"),
    ("psf", "optics.focal_pitch_m=2e-5",  # the focal sampling does not alias
     "optics.focal_pitch_m = 2e-05: the focal sampling would alias the intensity PSF: 0.909 samples per "
     "lambda*f/W_a, need >= 2, i.e. focal_pitch_m <= 9.09e-06 m"),
    ("psf", "optics.pupil_pitch_m=1e-4",  # the focal window fits in one period of the sampled pupil's spectrum
     "optics.pupil_pitch_m = 0.0001: the focal window (160 x 5.4e-06 m = 0.000864 m) is wider than the period "
     "lambda*f/pupil_pitch = 0.0006963 m of the sampled pupil's spectrum, so it would alias: need pupil_pitch_m <= "
     "8.059e-05 m or a smaller focal_n"),
    # ---- root keys and logging -----------------------------------------------------------------------------
    ("psf", "seed=abc", "seed = 'abc': must be an integer >= 0 and <= 1e+09"),
    ("psf", "seed=-1", "seed = -1: must be an integer >= 0 and <= 1e+09"),
    ("psf", "logging.tensorboard=maybe", "logging.tensorboard = 'maybe': must be true or false"),
    ("psf", "+logging.foo=1", "logging.foo = 1: unknown key; allowed: log_every, tensorboard"),
    ("psf", "+foo=1", "foo = 1: unknown key for +experiment=psf; allowed: task, seed, device, threads, deterministic, "
     "optics, material, mask, sensor, model, data, trainer, metrics, logging, evaluate, debug, precision, "
     "timing_repeats"),
    ("psf", "deterministic=maybe", "deterministic = 'maybe': must be auto, true or false"),
    ("baseline", "+checkpoint=x", "checkpoint = 'x': unknown key for +experiment=baseline; allowed: task, seed, "
     "device, threads, deterministic, optics, material, mask, sensor, model, data, trainer, metrics, logging, "
     "evaluate, debug, init"),
    # ---- simulate and data ---------------------------------------------------------------------------------
    ("simulate", "simulate.laser_strengths=5", "simulate.laser_strengths = 5: must be a non-empty list of laser "
     "strengths >= 0"),
    ("simulate", "simulate.laser_angle_rad=5", "simulate.laser_angle_rad = 5: must be [n_u, n_v] in radians"),
    ("simulate", "simulate.laser_angle_rad=[nan,0]", "simulate.laser_angle_rad[0] = nan: must be a finite number "
     ">= -1.5708 and <= 1.5708"),  # an incidence beyond 90 degrees never reaches the aperture
    ("simulate", "simulate.params.alpha_b=-1", "simulate.params.alpha_b = -1: must be a finite number >= 0"),
    ("simulate", "+simulate.params.foo=1", "simulate.params.foo = 1: is not a scene parameter; allowed: alpha_l, "
     "alpha_b, laser_angle_rad, c1, c2, dark_current_mean_e, read_noise_mean_e, read_noise_std_e, exposure_s"),
    ("simulate", "+simulate.params.alpha_l=1", "simulate.params.alpha_l = 1: is set by simulate.laser_strengths, "
     "not here"),
    ("simulate", "+simulate.foo=1",
     "simulate.foo = 1: unknown key; allowed: laser_angle_rad, laser_strengths, params, scenes, timing_repeats"),
    ("simulate", "+data.foo=1", "data.foo = 1: unknown key; allowed: batch_size, cache_mb, flips, folder, "
     "image_size, mask_draws, mask_every, mask_jitter, mask_lsr, masks, padded_size, params, scales, scenes, "
     "split_seed, test_fraction"),
    # ---- data.masks: a restorer trained over a pool of masks ------------------------------------------------
    ("baseline", "data.masks=published", "data.masks = 'published': must be a list of masks, each 'published', "
     "'defocus:R' (R in rad, 0 < R <= 200), 'random:FAMILY' or 'random:FAMILY:N' (N random masks of a family) or "
     "the path of a mask record (best_mask.json, learned_mask.json), or null for the configured mask alone"),
    ("baseline", "data.masks=[]", "data.masks = []: must be a non-empty list of masks, each 'published', "
     "'defocus:R' (R in rad, 0 < R <= 200), 'random:FAMILY' or 'random:FAMILY:N' (N random masks of a family) or "
     "the path of a mask record (best_mask.json, learned_mask.json), or null for the configured mask alone"),
    ("baseline", "data.scales=[96,96]", "data.scales = [96, 96]: must be a non-empty list of integer pixel scales "
     "in [8, sensor.resolution], or null (each scale once)"),
    ("baseline", "data.mask_lsr=[0.1,0.01]", "data.mask_lsr = [0.1, 0.01]: must be [lo, hi] with 0 < lo < hi <= 1 "
     "(the sampled LSR of the random pool members)"),
    ("baseline", "data.masks=[published,defocus:0]", "data.masks[1] = 'defocus:0': a defocus member is "
     "'defocus:R' with R a number of rad in (0, 200]"),
    ("baseline", "data.masks=[defocus:abc]", "data.masks[0] = 'defocus:abc': a defocus member is 'defocus:R' with "
     "R a number of rad in (0, 200]"),
    ("baseline", "data.masks=[/nonexistent.json]", "data.masks[0] = '/nonexistent.json': is neither 'published', "
     "'defocus:R' nor an existing mask record file"),
    ("baseline", "data.masks=[published] data.mask_every=0", "data.mask_every = 0: must be an integer >= 1"),
    ("baseline", "data.masks=[published] data.mask_jitter=-1", "data.mask_jitter = -1: must be a finite number >= 0 "
     "and <= 10"),
    ("joint", "data.masks=[published]", "data.masks = ['published']: trains one restorer over a pool of frozen "
     "masks (+experiment=baseline data.masks=[...]); a joint run trains one mask: leave it null and warm-start "
     "from such a restorer with init.checkpoint=PATH"),
    ("simulate", "data.image_size=4096 data.padded_size=4096", "data.image_size = 4096: must be <= "
     "sensor.resolution (2532): the sensor is binned to the network resolution, never upsampled"),
    ("simulate", "data.padded_size=100000",  # named as typed (it was sensor.padded_size, a key nobody typed)
     "data.padded_size = 100000: must be an integer >= 8 and <= 65536"),
    ("simulate", "+sensor.image_size=64",
     "sensor.image_size = 64: unknown key: the network resolution is data.image_size"),
    # ---- model, losses, evaluation, geometry (baseline) ----------------------------------------------------
    ("baseline", "model.widths=5",
     "model.widths = 5: must be a list of at least 1 positive integers, or null for the size preset's"),
    ("baseline", "model.widths=[]",
     "model.widths = []: must be a list of at least 1 positive integers, or null for the size preset's"),
    ("baseline", "model.loss.vgg_layers=5", "model.loss.vgg_layers = 5: must be a list of VGG19 feature layers "
     "(indices 0..36 or names such as relu3_4)"),
    ("baseline", "model.loss.vgg_layers=[99]", "model.loss.vgg_layers[0] = 99: must be an index 0..36 or a name "
     "such as relu1_1, relu1_2, relu2_1, relu2_2, relu3_1, relu3_2, relu3_3, relu3_4, relu4_1, relu4_2, relu4_3, "
     "relu4_4, relu5_1, relu5_2, relu5_3, relu5_4"),
    ("baseline", "evaluate.laser_strengths=5", "evaluate.laser_strengths = 5: must be a list of the paper's "
     "strengths 0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6"),
    ("baseline", "evaluate.stages=H1",
     "evaluate.stages = 'H1': must be a list of robustness stages from E1, E2, M, H1, H2 (or [])"),
    ("baseline", "evaluate.laser_angle_rad=5",
     "evaluate.laser_angle_rad = 5: must be [n_u, n_v] in radians, or null"),
    ("baseline", "evaluate.laser_angle_rad=[nan,0]", "evaluate.laser_angle_rad[0] = nan: must be a finite number"),
    ("baseline", "+evaluate.foo=1", "evaluate.foo = 1: unknown key; allowed: batch_size, dists_weights, "
     "laser_angle_rad, laser_strengths, lpips_weights, max_scenes, scenes, split, stages, tuning_size"),
    ("baseline", "data.image_size=48 data.padded_size=50",  # the PSF kernel fits the padded sensor image
     "data.padded_size = 50: must be >= data.image_size + PSF kernel - 1 = 48 + 5 - 1 = 52 at this pitch, so that "
     "deconvolution does not wrap"),
    ("joint", "codesign.lsr_max=best", "codesign.lsr_max = 'best': must be null (the protocol's default), start (the "
     "start mask's), published, published/K (K > 1) or a number in (0, 1]"),
    ("joint", "codesign.lsr_max=published/0.5", "codesign.lsr_max = 'published/0.5': must be null (the protocol's "
     "default), start (the start mask's), published, published/K (K > 1) or a number in (0, 1]"),
    ("joint", "codesign.protocol=both", "codesign.protocol = 'both': must be one of codesign, single"),
    ("joint", "codesign.design=halfring", "codesign.design = 'halfring': must be one of pixel, spiral, spline, "
     "zernike"),
    ("joint", "codesign.finetune_steps=0", "codesign.finetune_steps = 0: must be an integer >= 1 and <= 1e+07"),
    ("joint", "search.lsr_ceiling=0.001", "search.lsr_ceiling = 0.001: is set by the main job from codesign.lsr_max "
     "(give codesign.lsr_max instead)"),
    ("joint", "codesign.mask_lr=-1", "codesign.mask_lr = -1: must be a finite number >= 0 and <= 10"),
    ("joint", "+init.foo=1", "init.foo = 1: unknown key; allowed: checkpoint"),
    ("joint", "init.checkpoint=/nonexistent/ck.pt", "init.checkpoint = '/nonexistent/ck.pt': no such checkpoint file"),
    ("joint", "metrics.mtf_band=[0.5,0.2]", f"metrics.mtf_band = [0.5, 0.2]: {MTF_BAND}, beyond which the MTF is 0)"),
    # ---- fabrication export and tolerance --------------------------------------------------------------------
    ("export", "export.levels=1", "export.levels = 1: must be an integer >= 2 and <= 256"),
    ("export", "export.size_m=0.002", "export.size_m = 0.002: the plate must hold the aperture's support "
     "(0.00398 m): must be >= 0.004 m at export.pitch_m = 8e-06, or null"),
    ("export", "material=custom material.coefficients=[0.5]",
     "material.coefficients = [0.5]: give n = 0.5 at 0.633 um: a mask material needs n > 1"),
    ("export", "material.formula=abbe", "material.formula = 'abbe': must be one of sellmeier, cauchy, constant"),
    ("export", "mask.init=/nonexistent.json", "mask.init = '/nonexistent.json': must be null or the path of a mask "
     "record (best_mask.json of +experiment=mask_search, learned_mask.json of joint, mask.json of psf); no such "
     "file"),
    ("tolerance", "tolerance.samples=0", "tolerance.samples = 0: must be an integer >= 1 and <= 1e+06"),
    ("tolerance", "tolerance.lsr_ceiling=published", "tolerance.lsr_ceiling = 'published': must be auto or a "
     "number > 0"),
]


@pytest.mark.parametrize("experiment,overrides,message", ROWS, ids=[r[1] for r in ROWS])
def test_bad_value_stops_before_any_work_naming_key_and_allowed(experiment, overrides, message, monkeypatch,
                                                                capsys, tmp_path):
    line = config_error(monkeypatch, capsys, tmp_path / "run", f"+experiment={experiment}", "debug=smoke",
                        *overrides.split())
    assert line == f"codesign: configuration error: {message}"
    assert not (tmp_path / "run").exists()  # a refused run leaves no run dir behind


@pytest.mark.parametrize("experiment", sorted(EXPERIMENTS))
def test_root_key_allowlist_accepts_every_shipped_config(experiment):
    # the unknown-root-key check must never refuse what conf/experiment/<name>.yaml itself sets
    for extra in ([], ["debug=smoke"]):
        cfg = compose_cfg(f"+experiment={experiment}", *extra)
        assert set(cfg) <= set(root_keys(experiment)), sorted(set(cfg))


@pytest.mark.parametrize("content,message", [
    ('{"kind": "halfring", "r": [13.6, 91.8, 6.3], "theta": [1.86, 1.09]}',
     "its r and theta must be non-empty lists of numbers of equal length (got [13.6, 91.8, 6.3] and [1.86, 1.09])"),
    ('{"kind": "halfring", "r": [NaN], "theta": [1.0]}', "its r and theta hold NaN or Infinity (got [nan] and [1.0])"),
    ('{"kind": "halfring", "r": [1.0, 2', "cannot be read as JSON (Expecting ',' delimiter: line 1 column 34 "
                                          "(char 33))"),
    ('[1, 2]', f"the file holds kind None, not a mask family ({', '.join(families())})"),
    ('{"kind": "spiral", "charge": 2.0, "axicon_cycles": 3.0, "defocus_rad": 0.0, "charg": 5.0, "note": "x"}',
     "its key(s) charg, note are not keys of a spiral record (allowed: axicon_bounds, axicon_cycles, charge, "
     "charge_bounds, check_agree, defocus_bounds, defocus_rad, feasible, kind, levels, lsr, lsr_limit, "
     "lsr_over_limit, lsr_sampled, lsr_smooth, mtf_mean, optics, partial, phase_resolved, restorability, "
     "stop_reason, window_energy)"),
], ids=["unequal-rings", "nan", "truncated", "not-a-mask", "unknown-keys"])
def test_mask_init_file_with_bad_rings(tmp_path, monkeypatch, capsys, content, message):
    path = tmp_path / "best_mask.json"
    path.write_text(content)
    line = config_error(monkeypatch, capsys, tmp_path / "run", "+experiment=psf", "debug=smoke", f"mask.init={path}")
    assert line == (f"codesign: configuration error: mask.init = '{path}': must be null or the path of a mask record "
                    f"(best_mask.json of +experiment=mask_search, learned_mask.json of joint, mask.json of psf); "
                    f"{message}")


def test_cli_unknown_experiment_lists_the_available_ones(tmp_path):
    proc = run_codesign("+experiment=psff", f"hydra.run.dir={tmp_path / 'run'}")
    assert proc.returncode == 1  # Hydra's own composition error, before codesign runs
    assert "Could not find 'experiment/psff'" in proc.stderr
    assert re.search(r"Available options in 'experiment':\s+" + r"\s+".join(EXPERIMENTS), proc.stderr), proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "run").exists()
