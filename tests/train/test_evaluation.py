"""Evaluation helpers: affine matching, calibration, black level, padding; the evaluator on a tiny setup."""
from __future__ import annotations

import pytest
import torch

from codesign.models.wiener import classical_wiener_sweep
from codesign.train.evaluation import (NSR_GRID, Evaluator, affine_match, centre, conditions, fit_affine,
                                      flat_summary, remove_black_level, replicate_pad, tune_nsr)
from tests.train._util import tiny_trainer


def test_affine_match_recovers_an_affine_copy_exactly():
    t = torch.rand(3, 1, 16, 16, dtype=torch.float64) * 0.8 + 0.1
    x = 2.5 * t - 0.3
    assert torch.allclose(affine_match(x, t), t, atol=1e-12)
    flat = torch.full_like(t, 0.4)  # no variance: the best affine map is the target's mean
    assert torch.allclose(affine_match(flat, t), t.mean(dim=(-2, -1), keepdim=True).expand_as(t))


def test_fit_affine_is_least_squares():
    x = torch.linspace(0, 1, 100, dtype=torch.float64)
    a, c = fit_affine(x, 3 * x + 0.5)
    assert a == pytest.approx(3) and c == pytest.approx(0.5)


def test_black_level_only_on_the_field_and_replicate_padding():
    s = torch.zeros(2, 1, 8, 8)
    s[..., 2:6, 2:6] = 0.5
    batch = {"sensor": s, "read_noise_mean_e": torch.tensor([255.0, 510.0])}
    out = remove_black_level(batch, 25500.0)
    assert torch.allclose(out[0, 0, 2:6, 2:6], torch.full((4, 4), 0.49))
    assert torch.allclose(out[1, 0, 2:6, 2:6], torch.full((4, 4), 0.48))
    assert torch.count_nonzero(out[..., :2, :]) == 0
    x = torch.arange(64.0).view(1, 1, 8, 8)
    p = replicate_pad(x, 4)
    assert torch.equal(p[..., 2:6, 2:6], x[..., 2:6, 2:6]) and torch.equal(p[0, 0, 0, 2:6], x[0, 0, 2, 2:6])


def test_tune_nsr_takes_the_least_pooled_error_after_the_gain_offset_match():
    """The one Wiener nsr tuning: candidates in NSR_GRID order, scored on the field of view after the per-image
    gain/offset match (an affine copy of the target is the best candidate)."""
    g = torch.Generator().manual_seed(0)
    target = torch.rand(2, 1, 8, 8, generator=g)
    padded = torch.nn.functional.pad(target, (2, 2, 2, 2))  # the candidates carry a border beyond the field
    outputs = [padded + 0.3 * torch.rand(padded.shape, generator=g) for _ in NSR_GRID]
    outputs[5] = 0.5 * padded + 0.1
    outputs[7] = padded + 0.01 * torch.rand(padded.shape, generator=g)
    assert tune_nsr(outputs, target, 8) == NSR_GRID[5]


def test_conditions_and_flat_summary():
    assert conditions((0.0, 1e3, 1e6), ("E1", "H2")) == ["laser_0", "laser_1e3", "laser_1e6", "E1", "H2"]
    flat = flat_summary({"laser_0": {"sgan": {"psnr": 20.0}}})
    assert flat == {"psnr_sgan_laser_0": 20.0}


def test_evaluator_tunes_and_scores_every_method(tmp_path):
    tr = tiny_trainer(tmp_path)
    ev = Evaluator(tr.model, tr.model.generators(), tr.data, batch_size=8)
    calib = ev.tune(tr.data.validation_batch(2))
    assert calib["nsr"]["wiener"] in NSR_GRID and calib["nsr"]["g1_wiener"] in NSR_GRID
    scenes = tr.data.source.fixed_batch(tr.data.source.split_names("test"), tr.data.camera.scene_size)
    batch = tr.data.preset_batch(scenes, "laser_1e6", seed=3)
    images = ev.restore_all(batch)
    assert set(images) == {"sensor", "wiener", "g1_wiener", "sgan"} == set(ev.methods)
    for x in images.values():
        assert x.shape == (scenes.shape[0], 1, 48, 48) and 0 <= float(x.min()) and float(x.max()) <= 1
    target = batch["scene"][..., 8:56, 8:56]
    table = ev.score(images, target)
    for row in table.values():
        assert row["psnr_matched"] >= row["psnr"] - 1e-4  # the per-image least-squares fit can only help MSE
        assert set(row) >= {"one_minus_mse", "psnr", "ssim", "ms_ssim", "psnr_matched", "ssim_matched"}


def test_classical_wiener_deblurs_a_noise_free_capture(tmp_path):
    """With the true PSF and no noise, the tuned Wiener baseline must restore structure the sensor image lacks."""
    tr = tiny_trainer(tmp_path, "data.image_size=96", "data.padded_size=128", "optics.focal_n=480")
    scenes = tr.data.source.fixed_batch(["chelsea", "checkerboard"], tr.data.camera.scene_size)
    quiet = dict(c1=0.0, c2=0.0, read_noise_std_e=0.0, dark_current_mean_e=0.0)
    ev = Evaluator(tr.model, tr.model.generators(), tr.data, batch_size=8)
    ev.tune(tr.data.preset_batch(scenes, "laser_0", seed=1, **quiet))
    batch = tr.data.preset_batch(scenes, "laser_0", seed=2, **quiet)
    table = ev.score(ev.restore_all(batch), batch["scene"][..., 16:112, 16:112])
    assert table["wiener"]["psnr_matched"] > table["sensor"]["psnr_matched"] + 3.0, table



def test_baselines_are_tuned_for_each_scored_condition(tmp_path):
    """One tuning batch from the training distribution (lasers, every exposure) left Wiener's output uncorrelated
    with most scenes: every nsr scored alike, the choice was noise (nsr 100 here: Wiener 32.0 dB below the sensor
    image's 33.0 at alpha_l = 0). Tuned per condition on training crops, it deblurs: the nsr is the grid point of
    least pooled error after the per-image gain/offset match, on the tuning crops under that condition."""
    tr = tiny_trainer(tmp_path, "data.image_size=96", "data.padded_size=128", "optics.focal_n=480")
    scenes = tr.data.source.fixed_batch(tr.data.source.split_names("test"), tr.data.camera.scene_size)
    ev = Evaluator(tr.model, tr.model.generators(), tr.data, batch_size=8)
    tuning = tr.data.validation_scenes(8)
    ev.tune_per_condition(tuning, seed=5)
    _, _, _, table = ev.score_preset(scenes, "laser_0", seed=3)
    assert table["wiener"]["psnr_matched"] > table["sensor"]["psnr_matched"] + 1.0, table
    ev.score_preset(scenes, "laser_1e6", seed=4)
    assert set(ev.calib_by_condition) == {"laser_0", "laser_1e6"}
    batch = tr.data.preset_batch(tuning, "laser_0", seed=5)
    target, n = centre(batch["scene"], 96), 96
    y = replicate_pad(remove_black_level(batch, tr.data.camera.sensor.full_well_e), n)
    errors = [float((affine_match(centre(x, n), target) - target).square().mean())
              for x in classical_wiener_sweep(y, tr.data.otf, NSR_GRID)]
    assert ev.calib_by_condition["laser_0"]["nsr"]["wiener"] == NSR_GRID[errors.index(min(errors))]
