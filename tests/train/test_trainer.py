"""The restoration trainer: step order, optimizers and schedule, initialization, EMA, NaN guard, checkpoints."""
from __future__ import annotations

import math
import os

import pytest
import torch

from codesign.train.checkpoint import load_checkpoint, save_checkpoint
from codesign.models.losses import LossWeights
from codesign.train.spec import TrainerSpec
from codesign.train.optim import EMA
from codesign.errors import ConfigError
from tests.train._util import tiny_trainer

NO_IO = dict(val_every=0, checkpoint_every=0, image_every=0)


def _params(modules):
    return [p.detach().clone() for m in modules for p in m.parameters()]


def _same(a, b):
    return all(torch.equal(x, y) for x, y in zip(a, b))


def test_critic_step_moves_only_critics(tmp_path):
    tr = tiny_trainer(tmp_path)
    batch = tr.data.train_batch(0)
    g0, d0 = _params(tr.model.generators()), _params(tr.model.critics())
    terms = tr.update.critic_update(batch)
    assert _same(g0, _params(tr.model.generators()))
    assert not _same(d0, _params(tr.model.critics()))
    assert all(p.grad is None for g in tr.model.generators() for p in g.parameters())
    assert math.isfinite(float(terms["critic_total"].detach()))


def test_generator_step_freezes_critics(tmp_path):
    tr = tiny_trainer(tmp_path)
    batch = tr.data.train_batch(0)
    g0, d0 = _params(tr.model.generators()), _params(tr.model.critics())
    tr.update.generator_update(batch)
    assert _same(d0, _params(tr.model.critics()))
    assert all(p.grad is None for d in tr.model.critics() for p in d.parameters())
    assert all(p.requires_grad for d in tr.model.critics() for p in d.parameters())  # unfrozen after
    assert not _same(g0, _params(tr.model.generators()))


def test_adam_groups_and_schedule(tmp_path):
    tr = tiny_trainer(tmp_path, steps=16)
    for opt in (tr.opt_g, tr.opt_d):
        lrs = {g["name"]: g["lr"] for g in opt.param_groups}
        assert lrs == {"weights": 2e-4, "biases": 4e-4}
        assert opt.defaults["betas"] == (0.9, 0.999)
        biases = opt.param_groups[1]["params"]
        assert biases and all(p.dim() == 1 for p in biases)
    spec = TrainerSpec(steps=400)
    # Sec. 6.2 on 400 "epochs": 1 until 100, halved until 150, then x0.3 every 50
    assert [spec.lr_factor(s) for s in (0, 99, 100, 149, 150, 199, 200, 399)] == pytest.approx(
        [1, 1, 0.5, 0.5, 0.15, 0.15, 0.045, 0.5 * 0.3**5])


def test_orthogonal_init_zero_biases_zero_attention_projection(tmp_path):
    tr = tiny_trainer(tmp_path)
    conv = tr.model.g1.head[0][0]
    w = conv.weight.detach().flatten(1)  # (out, in*k*k): rows orthonormal
    assert torch.allclose(w @ w.T, torch.eye(w.shape[0]), atol=1e-5)
    assert torch.count_nonzero(conv.bias) == 0
    att = tr.model.g1.body.encoder[0].attention
    assert torch.count_nonzero(att.proj.weight) == 0 and torch.count_nonzero(att.proj.bias) == 0


def test_ema_is_exponential_average():
    lin = torch.nn.Linear(2, 2)
    ema = EMA([lin], 0.9)
    old = lin.weight.detach().clone()
    with torch.no_grad():
        lin.weight.add_(1.0)
    ema.update([lin])
    assert torch.allclose(ema.shadow[0].weight, 0.9 * old + 0.1 * (old + 1.0))


def test_non_finite_loss_skips_update_on_the_device_and_reports_it_at_logging(tmp_path, caplog):
    tr = tiny_trainer(tmp_path)
    p0 = _params(tr.model.generators())
    loss = sum(p.sum() for p in tr.model.g1.parameters()) * float("nan")
    applied = tr.guard(tr.opt_g, loss, tr.model.generators())
    assert isinstance(applied, torch.Tensor) and applied.dim() == 0 and not bool(applied)
    assert tr.skipped == 1 and _same(p0, _params(tr.model.generators()))
    assert all(int(st["step"]) == 0 for st in tr.opt_g.state.values())  # the skipped step is not counted either
    with caplog.at_level("WARNING", logger="codesign.train"):
        tr.guard.report(tr.step)
        tr.guard.report(tr.step)  # reported once
    assert caplog.text.count("1 update(s) skipped since the last report (1 non-finite loss, 0 non-finite "
                             "gradient)") == 1
    finite = sum(p.sum() for p in tr.model.g1.parameters())
    assert bool(tr.guard(tr.opt_g, finite, tr.model.generators())) and not _same(p0, _params(tr.model.generators()))


def test_an_update_that_leaves_weights_non_finite_is_undone_with_the_adam_moments(tmp_path, caplog):
    """Finite loss and gradients, but a step so large the weights overflow to inf (a huge learning rate): the
    weights and Adam's moments go back to their values before the step, on the device, and it is reported."""
    tr = tiny_trainer(tmp_path)
    finite = sum(p.sum() for p in tr.model.g1.parameters())
    assert bool(tr.guard(tr.opt_g, finite, tr.model.generators()))  # one good step: Adam has its moments
    p0 = _params(tr.model.generators())
    m0 = {k: v.clone() for st in tr.opt_g.state.values() for k, v in st.items() if k == "exp_avg"}
    states0 = [{k: v.clone() for k, v in st.items()} for st in tr.opt_g.state.values()]
    for group in tr.opt_g.param_groups:
        group["lr"] = 1e39  # times an Adam step of ~1: beyond float32's 3.4e38
    loss = sum(p.sum() for p in tr.model.g1.parameters())
    applied = tr.guard(tr.opt_g, loss, tr.model.generators())
    assert m0 and not bool(applied) and tr.rollbacks == 1 and tr.skipped == 0
    assert _same(p0, _params(tr.model.generators()))
    for before, st in zip(states0, tr.opt_g.state.values()):
        assert all(torch.equal(before[k], st[k]) for k in before)
    with caplog.at_level("WARNING", logger="codesign.train"):
        tr.guard.report(tr.step)
    assert "1 update(s) left non-finite weights and were undone since the last report" in caplog.text


def test_twenty_steps_lower_the_reconstruction_loss(tmp_path):
    tr = tiny_trainer(tmp_path, steps=20)  # the full SGAN-B objective, Sec. 6.2 learning rates
    val = tr.data.validation_batch(4)

    def rec():
        with torch.no_grad():
            out = tr.model(val["sensor"], tr.data.otf)
            terms = tr.update.generator_losses(val, out)
        return float(tr.model.weights.l1_stage1 * terms["rec1"] + tr.model.weights.l1_stage2 * terms["rec2"])

    before = rec()
    tr.fit(progress_every=100)
    after = rec()
    assert tr.step == 20 and tr.skipped == 0
    assert after < 0.9 * before, (before, after)


RESUME_TOL = 0.0  # resumed against uninterrupted: bit-identical (benchmarks/bench_accuracy.py reports the difference)


def _resume_runs(tmp_path):
    """Two steps, a checkpoint, two more steps; a trainer of another seed loads the checkpoint and does the same two
    steps. Returns (uninterrupted trainer, resumed trainer, the resumed one's step at load, the uninterrupted run's
    last two step logs, the resumed run's, the checkpoint path)."""
    a = tiny_trainer(tmp_path / "a", steps=4)
    a.train_step()
    a.train_step()
    path = a.save(tmp_path / "ck.pt")
    later = [a.train_step() for _ in range(2)]
    b = tiny_trainer(tmp_path / "b", steps=4, seed=123)  # different seed: everything must come from the file
    b.load_state_dict(load_checkpoint(path))
    step_at_load = b.step
    again = [b.train_step() for _ in range(2)]
    return a, b, step_at_load, later, again, path


def resume_difference(runs: tuple | None = None, tmp_path=None) -> float:
    """Largest |difference| between the resumed and the uninterrupted run: their last two steps' logged terms and
    their weights after them; inf if the logs name other terms, NaN if a value is NaN (``runs``: the _resume_runs
    result, computed in ``tmp_path`` when not given)."""
    a, b, _, later, again, _ = _resume_runs(tmp_path) if runs is None else runs
    if len(later) != len(again) or any(x.keys() != y.keys() for x, y in zip(later, again)):
        return math.inf
    diffs = [abs(float(x[k]) - float(y[k])) for x, y in zip(later, again) for k in x]
    diffs += [float((p - q).abs().max()) for p, q in zip(_params([a.model]), _params([b.model]))]
    return math.nan if any(math.isnan(d) for d in diffs) else max(diffs)


def test_resume_reproduces_the_next_steps_exactly(tmp_path):
    runs = _resume_runs(tmp_path)
    a, b, step_at_load, later, again, path = runs
    assert step_at_load == 2
    assert later == again
    assert _same(_params([a.model]), _params([b.model]))
    assert resume_difference(runs) <= RESUME_TOL
    st = load_checkpoint(path)
    assert {"model", "opt_g", "opt_d", "sched_g", "sched_d", "step", "rng", "config"} <= set(st)


def test_checkpoint_write_is_atomic(tmp_path):
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, {"model": {}, "config": {"v": 1}})
    with pytest.raises(Exception):
        save_checkpoint(path, {"model": {}, "config": {"v": 2}, "bad": lambda: 0})  # lambdas do not pickle
    assert load_checkpoint(path)["config"] == {"v": 1}
    assert os.listdir(tmp_path) == ["checkpoint.pt"]


def test_load_checkpoint_errors(tmp_path):
    with pytest.raises(ConfigError, match="checkpoint = .*nope.pt.*: no such checkpoint file"):
        load_checkpoint(tmp_path / "nope.pt")
    torch.save({"weights": 1}, tmp_path / "other.pt")
    with pytest.raises(ConfigError, match="is not a codesign checkpoint"):
        load_checkpoint(tmp_path / "other.pt")


@pytest.mark.parametrize("key,value,msg", [
    ("betas", [0.9], "must be \\[beta1, beta2\\]"),
    ("steps", 0, "must be an integer >= 1"),
    ("factor", 1.5, "must be a finite number > 0 and <= 1"),
    ("ema", 1.0, "must be a finite number > 0 and < 1"),
])
def test_trainer_spec_errors(key, value, msg):
    with pytest.raises(ConfigError, match=f"trainer.{key} = .*: {msg}"):
        TrainerSpec.from_config({key: value})


def test_loss_weights_reject_negative_and_unknown():
    with pytest.raises(ConfigError, match="model.loss.gp = -1"):
        LossWeights.from_config({"gp": -1})
    with pytest.raises(ConfigError, match="model.loss.l2 = .*unknown key"):
        LossWeights.from_config({"l2": 1})


def test_vgg_term_off_without_weights_and_a_missing_file_stops_before_training(tmp_path):
    tr = tiny_trainer(tmp_path, "model=sgan_e")
    assert tr.model.weights.vgg == 100.0 and tr.model.vgg is None
    assert tr.model.loss_status == "off: no VGG19 weights configured (model.loss.vgg_weights)"
    with pytest.raises(ConfigError, match="model.loss.vgg_weights = .*missing_vgg19.pth"):
        tiny_trainer(tmp_path, "model=sgan_e", f"model.loss.vgg_weights={tmp_path / 'missing_vgg19.pth'}")


@pytest.mark.parametrize("variant", ["sgan_b", "sgan_e", "sgan_f"])
def test_every_variant_trains_one_step_with_its_preset(tmp_path, variant):
    tr = tiny_trainer(tmp_path, f"model={variant}", steps=1)
    terms = tr.train_step()
    expected = {"sgan_b": {"mdf", "adv"}, "sgan_e": {"mdf", "adv"}, "sgan_f": {"mdf", "adv", "fft"}}[variant]
    assert expected <= set(terms) and all(math.isfinite(v) for v in terms.values())


def test_generator_total_is_the_weighted_sum_of_its_terms(tmp_path):
    tr = tiny_trainer(tmp_path, "model=sgan_f")
    batch = tr.data.train_batch(0)
    with torch.no_grad():
        terms = tr.update.generator_losses(batch, tr.model(batch["sensor"], tr.data.otf))
    w = tr.model.weights
    expected = (w.l1_stage1 * terms["rec1"] + w.l1_stage2 * terms["rec2"] + w.adv * terms["adv"]
                + w.mdf * terms["mdf"] + w.fft * terms["fft"])
    assert (w.l1_stage1, w.l1_stage2, w.mdf, w.fft, w.adv) == (10.0, 10.0, 0.1, 100.0, 0.1)  # the SGAN-F preset
    torch.testing.assert_close(terms["generator_total"], expected)


def test_mdf_without_adversarial_training_is_refused():
    with pytest.raises(ConfigError, match="model.loss.mdf = 1.0: needs model.loss.adv > 0"):
        LossWeights.from_config({"adv": 0.0, "mdf": 1.0})


def test_resumed_seconds_count_the_checkpoints(tmp_path):
    """A resumed run's train_seconds are the checkpoint's plus its own (in process: the killed-and-resumed process
    pair is the slow level's test)."""
    a = tiny_trainer(tmp_path / "a", steps=2, **NO_IO)
    a.fit()
    state = a.state_dict()
    state["seconds"] = 1.0e6
    b = tiny_trainer(tmp_path / "b", steps=3, **NO_IO)
    b.load_state_dict(state)
    b.fit()
    assert b.step == 3 and 1.0e6 < b.train_seconds < 1.0e6 + 600


def test_ema_switched_on_at_resume_starts_from_the_loaded_weights(tmp_path):
    a = tiny_trainer(tmp_path / "a", steps=1, **NO_IO)
    a.fit()
    b = tiny_trainer(tmp_path / "b", steps=2, ema=0.99, seed=5, **NO_IO)  # other initial weights
    b.load_state_dict(a.state_dict())  # a checkpoint without EMA
    for shadow, g in zip(b.ema.shadow, a.model.generators()):
        assert all(torch.equal(s, t) for s, t in zip(shadow.state_dict().values(), g.state_dict().values()))
        assert not any(p.requires_grad for p in shadow.parameters())
