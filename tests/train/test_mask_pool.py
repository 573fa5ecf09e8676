"""data.masks: a restorer's training batches through a pool of frozen masks, each batch with its own mask's OTF."""
from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from codesign.errors import ConfigError
from codesign.experiments.evaluate import merged_eval_config
from codesign.train import checkpoint as ckpt
from codesign.train.data import SimulatedData
from codesign.train.mask_pool import MaskPool, build_mask_pool
from tests.train._util import CPU, tiny_cfg

POOL = "data.masks=[published,defocus:20,defocus:50]"


@pytest.fixture(scope="module")
def pooled():
    cfg = tiny_cfg(POOL, "data.mask_draws=1", "data.mask_jitter=0.1", "data.mask_every=3")
    data = SimulatedData(cfg, CPU, 0)
    data.use_pool(build_mask_pool(cfg, data.camera, 0))
    return cfg, data


def test_pool_holds_every_member_and_its_draws(pooled):
    _, data = pooled
    assert data.pool.names == ["published", "published draw 1", "defocus:20", "defocus:20 draw 1", "defocus:50",
                               "defocus:50 draw 1"]
    lsr = dict(zip(data.pool.names, data.pool.lsr()))
    # a stronger defocus spreads the focal spot over more pixels: a lower peak
    assert lsr["defocus:50"] < lsr["defocus:20"] < lsr["published"]
    for cam in data.pool.cameras:  # every member frozen, its optics on the shared optical system
        assert cam.system is data.camera.system
        assert not any(p.requires_grad for p in cam.mask.parameters())


def test_draws_scatter_around_their_member_by_the_jitter_within_bounds(pooled):
    _, data = pooled
    cams = dict(zip(data.pool.names, data.pool.cameras))
    base, drawn = cams["defocus:50"].mask.to_vector(), cams["defocus:50 draw 1"].mask.to_vector()
    lo, hi = cams["defocus:50 draw 1"].mask.bounds()
    assert bool(((drawn >= lo) & (drawn <= hi)).all())
    spread = float((drawn - base).square().mean().sqrt() / base.square().mean().sqrt())
    assert 0.08 < spread < 0.12  # the jitter 0.1, over the spline's many control values


def test_member_of_a_step_depends_on_seed_and_window_alone():
    pool = MaskPool([str(k) for k in range(5)], [None] * 5, every=3, seed=7)
    picks = [pool.index(s) for s in range(300)]
    assert picks == [MaskPool([str(k) for k in range(5)], [None] * 5, 3, 7).index(s) for s in range(300)]
    assert all(picks[s] == picks[s - s % 3] for s in range(300))  # one member per window of mask_every steps
    assert set(picks) == set(range(5))
    assert picks != [MaskPool([str(k) for k in range(5)], [None] * 5, 3, 8).index(s) for s in range(300)]


def test_training_batch_carries_its_members_otf_and_validation_keeps_the_configured_mask(pooled):
    _, data = pooled
    members = set()
    for step in range(0, 30, 3):
        cam = data.pool.camera(step)
        members.add(id(cam))
        assert torch.equal(data.train_batch(step)["otf"], cam.otf)
    assert len(members) > 1  # the batches come through several masks
    assert torch.equal(data.otf, data.camera.otf)
    assert "otf" not in data.validation_batch(2)


def test_pool_batch_equals_a_direct_simulation_through_the_member():
    cfg = tiny_cfg(POOL, "data.mask_every=1")
    a, b = SimulatedData(cfg, CPU, 3), SimulatedData(cfg, CPU, 3)
    a.use_pool(build_mask_pool(cfg, a.camera, 3))
    pool = build_mask_pool(cfg, b.camera, 3)
    for step in range(4):
        got = a.train_batch(step)
        want = b.simulate(*b.train_draw(step), camera=pool.camera(step))
        assert torch.equal(got["sensor"], want["sensor"])
        assert torch.equal(got["otf"], pool.camera(step).otf)


def test_trainable_mask_refuses_a_pool(pooled):
    cfg, data = pooled
    other = SimulatedData(cfg, CPU, 0)
    other.camera.set_trainable(True)
    with pytest.raises(ConfigError, match="trains a restorer over frozen masks"):
        other.use_pool(data.pool)


def test_evaluate_takes_a_typed_mask_over_the_checkpoints(pooled):
    cfg, _ = pooled
    here = OmegaConf.merge(cfg, {"mask": {"kind": "spline"}})
    kept = merged_eval_config(here, cfg, frozenset())
    assert kept.mask.kind == cfg.mask.kind
    typed = merged_eval_config(here, cfg, frozenset({"mask"}))
    assert typed.mask.kind == "spline"


def test_shipped_checkpoint_is_found_by_name_or_named_as_missing(tmp_path, monkeypatch):
    assert ckpt.checkpoint_path("some/run/checkpoint.pt") == ckpt.Path("some/run/checkpoint.pt")
    monkeypatch.setattr(ckpt, "PRETRAINED_DIR", tmp_path)
    with pytest.raises(ConfigError) as err:
        ckpt.load_checkpoint("pretrained", "init.checkpoint")
    assert str(err.value) == (f"init.checkpoint = 'pretrained': names the shipped restorer "
                              f"{tmp_path / ckpt.PRETRAINED['pretrained']}, which this installation lacks (reinstall "
                              "codesign, or give a checkpoint path)")
