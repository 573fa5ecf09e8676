"""model.level_head: the gain per image that brings a restoration to the scene's level (codesign/models/level.py),
its quantiles against torch's, its fit against a known law, and its fit at the end of a training (SGAN.calibrate)."""
from __future__ import annotations

import pytest
import torch

from codesign.models.level import (N_FEATURES, QUANTILES, LevelHead, best_log_gain, field_quantiles, fit_weight,
                                   level_features)
from codesign.train.checkpoint import load_checkpoint
from tests.train._util import tiny_trainer

F64 = torch.float64


def _images(n: int, seed: int = 0, p: int = 16) -> torch.Tensor:
    """Sensor-like images: a zero-padded border (the padding) around values in (0.05, 0.95)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.zeros(n, 1, p, p, dtype=F64)
    x[..., 2:-2, 3:-3] = 0.05 + 0.9 * torch.rand(n, 1, p - 4, p - 6, generator=g, dtype=F64)
    return x


def test_field_quantiles_are_torch_quantiles_of_the_field_pixels():
    x = _images(3)
    field = x > 0
    q = field_quantiles(x, field)
    expect = torch.stack([torch.quantile(x[i][field[i]], torch.tensor(QUANTILES, dtype=F64)) for i in range(3)])
    assert torch.allclose(q, expect, atol=1e-15, rtol=0)


def test_the_features_ignore_saturated_pixels():
    x = _images(2)
    sat = x.clone()
    sat[..., 5:8, 6:9] = 1.0  # a laser's footprint: the sensor saturated there
    assert not torch.equal(level_features(x, x), level_features(x, sat))
    kept = x.clone()
    kept[..., 5:8, 6:9] = 0.0  # the same as leaving those pixels out of the field
    assert torch.allclose(level_features(x, sat), level_features(x, kept), atol=1e-15, rtol=0)


def test_a_constant_exposure_law_is_recovered_exactly():
    scene = _images(40, seed=1)
    out = 0.4 * scene  # every restoration at 0.4 of the scene's level
    field = scene > 0
    t = best_log_gain(out, scene, field)
    assert torch.allclose(t, torch.full_like(t, -torch.log(torch.tensor(0.4, dtype=F64))), atol=1e-12)
    head = LevelHead()
    head.set_weight(fit_weight(level_features(out, scene), t))
    assert head.fitted
    assert torch.allclose(head.gain(out, scene), torch.full((40,), 2.5, dtype=F64), atol=1e-6)
    # the gain is scaled in log by 1 - p: a fully present laser leaves the image as it is
    p = torch.tensor([0.0, 0.5, 1.0], dtype=F64)
    g = head.gain(out[:3], scene[:3], p)
    assert torch.allclose(g, torch.tensor([2.5, 2.5 ** 0.5, 1.0], dtype=F64), atol=1e-6)


def test_an_unfitted_head_is_exactly_one_and_a_fit_needs_two_images():
    head = LevelHead()
    x = _images(2)
    assert not head.fitted and torch.equal(head.gain(x, x), torch.ones(2, dtype=F64))
    assert head.weight.shape == (N_FEATURES,)
    dark = torch.zeros_like(x)  # no positive gain brings black to the scene
    with pytest.raises(ValueError, match="the level fit needs at least 2 images with a positive best gain, got 0"):
        fit_weight(level_features(x, x), best_log_gain(dark, x, x > 0))


def test_a_training_fits_the_head_into_the_model_its_ema_and_the_checkpoint(tmp_path):
    tr = tiny_trainer(tmp_path, "model=sgan_b_gated", steps=2, ema=0.9, val_every=0, checkpoint_every=0,
                      image_every=0, calibrate_crops=64)
    assert tr.model.spec.level_head and not tr.model.g2.level.fitted
    tr.fit()
    unlasered = tr.data.unlasered_batch(8)
    assert float(unlasered["laser"].abs().max()) == 0.0

    def level_error() -> float:  # how far the restorations' mean brightness is from the scenes'
        out = tr.model.restore(unlasered["sensor"], tr.data.otf, tr.restoring_modules())["restored"]
        return float((out.mean() - unlasered["scene"].mean()).abs())

    before = level_error()
    facts = tr.calibrate()
    assert N_FEATURES < facts["level_head"]["crops"] <= 64  # trainer.calibrate_crops (rows with no gain left out)
    shadow = tr.restoring_modules()[2].level
    assert tr.model.g2.level.fitted and shadow.fitted
    assert torch.equal(tr.model.g2.level.weight, shadow.weight)
    saved = load_checkpoint(tmp_path / "checkpoint.pt")
    assert torch.equal(saved["model"]["g2.level.weight"], shadow.weight)
    assert saved["record"]["level_head"] == facts["level_head"]
    # the sensor sees alpha_b in [0.3, 0.7] of the scene: the fitted gain brings the output towards its level
    assert level_error() < 0.5 * before, (before, level_error())


def test_an_exposure_target_is_the_scene_at_the_exposure_the_sensor_saw(tmp_path):
    from codesign.models.sandwich import pyramid
    from codesign.models.sgan import _targets
    tr = tiny_trainer(tmp_path, "model=sgan_b_gated", "model.target_level=exposure", steps=1, val_every=0,
                      checkpoint_every=0, image_every=0)
    batch = tr.data.train_batch(0)
    a = batch["alpha_b"]
    assert a.shape == (batch["scene"].shape[0],) and bool(((a >= 0.3) & (a <= 0.7)).all())
    scene = pyramid(batch["scene"])
    for t, s in zip(_targets(dict(batch), "exposure"), scene):
        assert torch.allclose(t, a[:, None, None, None] * s, rtol=1e-6, atol=1e-7)
    for t, s in zip(_targets(dict(batch), "scene"), scene):
        assert torch.equal(t, s)
    with pytest.raises(ValueError, match="model.target_level=exposure needs the batch's alpha_b"):
        _targets({"scene": batch["scene"]}, "exposure")


@pytest.mark.parametrize("level", ["scene", "exposure"])
def test_held_to_the_exposure_a_lasered_output_gets_the_whole_gain(tmp_path, level):
    """A head fitted to a constant gain of 2 (its constant feature): held to the scene, a lasered output gets
    2 ** (1 - p); held to the exposure, every output gets 2."""
    tr = tiny_trainer(tmp_path, "model=sgan_b_gated", f"model.target_level={level}", steps=1, val_every=0,
                      checkpoint_every=0, image_every=0)
    model, gens = tr.model, tr.restoring_modules()
    batch = tr.data.validation_batch(4).copy()
    sensor = batch["sensor"].clone()
    sensor[..., 20:24, 20:24] = 1.0  # a laser's saturated footprint in every image: presence > 0
    plain = model.restore(sensor, tr.data.otf, gens)["restored"]
    weight = torch.zeros(N_FEATURES, dtype=F64)
    weight[0] = torch.log(torch.tensor(2.0, dtype=F64))
    gens[2].level.set_weight(weight)
    ratio = (model.restore(sensor, tr.data.otf, gens)["restored"] / plain).flatten(1)
    p = gens[2].laser_presence(sensor).detach().double()
    assert bool((p > 0.01).all())
    want = torch.full_like(p, 2.0) if level == "exposure" else 2.0 ** (1 - p)
    assert torch.allclose(ratio.double().median(1).values, want, rtol=1e-5)


@pytest.mark.parametrize("level", ["scene", "exposure"])
def test_held_to_the_exposure_the_objective_compares_g2s_output_before_the_gain(tmp_path, level):
    """A fitted head (a warm start's, a resumed finished run's) in training: held to the exposure, the L1 term
    compares G2's output before the gain with alpha_b * b, so fitting the head (constant gain 2) leaves every
    generator term as it was; held to the scene it compares the scaled output, so the term changes."""
    from codesign.models.restorer import TrainContext
    tr = tiny_trainer(tmp_path, "model=sgan_b_gated", f"model.target_level={level}", steps=1, val_every=0,
                      checkpoint_every=0, image_every=0)
    model, gens = tr.model, list(tr.model.generators())
    batch = tr.data.train_batch(0)
    ctx = TrainContext(critics=list(model.critics()))

    def rec2() -> float:
        with torch.no_grad():
            return float(model.generator_losses(batch, model.forward_with(gens, batch["sensor"], tr.data.otf),
                                                ctx)["rec2"])

    before = rec2()
    weight = torch.zeros(N_FEATURES, dtype=F64)
    weight[0] = torch.log(torch.tensor(2.0, dtype=F64))
    model.g2.level.set_weight(weight)
    after = rec2()
    if level == "exposure":
        assert after == before
    else:
        assert abs(after - before) > 1e-3 * before


def test_the_calibration_crops_are_checked():
    from codesign.errors import ConfigError
    from codesign.train.spec import TrainerSpec
    with pytest.raises(ConfigError, match=r"trainer.calibrate_crops = 2: must be an integer >= 4 and <= 65536"):
        TrainerSpec(calibrate_crops=2)
