"""Long CPU training under WGAN-GP with every image dazzled by a strong laser, on the project's own trainers.

The runs stay finite, the losses stay within bounds set from measured ranges, the networks keep learning, and a
NaN forced mid-run (into the critic's loss, a generator gradient, a simulated batch) skips exactly the update it
poisons: that side's weights and Adam moments are left as they were, the skip is counted and logged, and the
following steps are finite again. The short unit checks of the same guards are in tests/train (test_trainer:
_apply on a NaN loss; test_joint: NaN generator loss, NaN mask gradient, NaN mask restored); this file is the
long, realistic version with both critics and generators and the joint mask path.

Measured ranges quoted below: tiny SGAN-B, 32 px images padded to 48, batch 2, seed 0, 1 thread, torch 2.13 CPU.
"""
from __future__ import annotations

import copy
import logging
import math
import statistics
from pathlib import Path

import pytest
import torch

from codesign.models import losses
from codesign.train.lsr_constraint import snapshot
from tests.train._util import joint_trainer, tiny_trainer

CPU = torch.device("cpu")
# Every image dazzled: alpha_l drawn from [1e6, 1e8] instead of the paper's [0, 2e6]; 1e8 is the top of the range
# the float32 sensor model is tested for (tests/stress/test_laser_sweep.py). The laser lands on the sensor in every
# batch, so every step trains on saturated pixels. Small images keep a step at ~0.25 s on one thread.
STRONG_LASER = ["data.params.alpha_l_range=[1.0e6,1.0e8]", "data.image_size=32", "data.padded_size=48"]
NO_IO = dict(val_every=0, checkpoint_every=0, image_every=0)

# Upper bounds on |term|, set from the ranges measured over 60-300 restoration steps and 80 joint steps (in
# brackets; the 200-step CI and 600-step long runs pass them too). Each leaves 4-20x of room, so that another
# trajectory (another CPU's rounding, other scene crops) passes, while a diverging GAN (losses growing by orders
# of magnitude, then Inf/NaN) fails.
BOUNDS = {
    # Charbonnier ~ mean |output - target| with targets in [0, 1]: 5 means the outputs have left the image range
    # [rec1 0.050..0.19, rec2 0.13..1.33]
    "rec1": 5.0, "rec2": 5.0,
    # critic outputs and features have no absolute scale in WGAN (no drift term), so these are only loose
    # [mdf 0.23..1.08, |adv| <= 1.05]
    "mdf": 20.0, "adv": 20.0,
    # Wasserstein estimates E D(real) - E D(fake) of critics kept ~1-Lipschitz by the penalty [|W| <= 0.87]
    "d1_wasserstein": 10.0, "d2_wasserstein": 10.0,
    # (|grad D| - 1)^2 (d2: summed over both scales): 1e4 means |grad D| ~ 100, 2.5x the steepest critic seen
    # (d2_gp spikes of 48-115 at orthogonal init and now and then later in the first trajectories; 797 and 1587
    # in single steps of a 60-step run after the data draws became per sample and Adam fused, a 1-ulp change of
    # the update that a GAN amplifies; the penalty pulls every spike back within a step or two) [d1_gp <= 0.51]
    "d1_gp": 1e4, "d2_gp": 1e4,
    # lambda_ADV (W1 + W2) + lambda_GP (gp1 + gp2) [critic_total 0.68..15870]; 200 rec1 + 50 rec2 + 50 mdf + adv
    # [generator_total 29..156]
    "critic_total": 1e5, "generator_total": 1e3,
}


def _record_saturation(tr) -> list[float]:
    """From now on, each training batch's saturated-pixel fraction is appended to the returned list."""
    draw, saturated = tr.data.train_batch, []

    def recording(step):
        batch = draw(step)
        saturated.append(float(batch["saturated"].float().mean()))
        return batch

    tr.data.train_batch = recording  # instance attribute: the trainer calls it, nothing else changes
    return saturated


def _train(tr, steps: int) -> list[dict]:
    return [tr.train_step() for _ in range(steps)]


# The penalty terms (and the critic total they dominate) may spike in a single step and come back: on another
# 2-core AMD EPYC (2026-11-26) the same seeded 100-step run had d2_gp 83,045 (critic_total 8.3e5) at step 36 alone,
# below 1e3 before and after, with learning unaffected. A diverging critic does not come back. So these may exceed
# their bound in at most SPIKES steps, each followed within RECOVERY steps by one under it, and never by SPIKE_CAP x.
SPIKY, SPIKES, RECOVERY, SPIKE_CAP = ("d1_gp", "d2_gp", "critic_total"), 3, 2, 100.0


def _check_finite_and_bounded(logs: list[dict]) -> None:
    over: dict[str, list[int]] = {}
    for k, terms in enumerate(logs):
        for name, value in terms.items():
            assert math.isfinite(value), f"step {k}: {name} = {value}"
            if name not in BOUNDS or abs(value) <= BOUNDS[name]:
                continue
            assert name in SPIKY and abs(value) <= SPIKE_CAP * BOUNDS[name], \
                f"step {k}: |{name}| = {abs(value):.4g} > {BOUNDS[name]:g}"
            over.setdefault(name, []).append(k)
    for name, steps in over.items():
        assert len(steps) <= SPIKES, f"|{name}| above {BOUNDS[name]:g} in {len(steps)} steps: {steps}"
        for k in steps:
            after = [abs(float(t[name])) for t in logs[k + 1:k + 1 + RECOVERY]]
            assert not after or min(after) <= BOUNDS[name], f"|{name}| did not come back after step {k}: {after}"


def validation_rec(tr) -> tuple[float, float]:
    """(rec1, rec2) on the fixed validation batch (own seeds: the same scenes, lasers and noise every call),
    simulated through the current mask."""
    val = tr.data.validation_batch(4)
    with torch.no_grad():
        terms = tr.update.generator_losses(val, tr.model(val["sensor"], tr.data.otf))
    return float(terms["rec1"]), float(terms["rec2"])


LEARNING_RATIO = 0.85  # rec1 and rec2 after / before must both fall below this (benchmarks/bench_accuracy.py)


def learning_ratio(before: tuple[float, float], after: tuple[float, float]) -> float:
    """The larger of rec1 after / before and rec2 after / before (validation_rec values)."""
    return max(a / b for a, b in zip(after, before))


def _check_learning(tr, before: tuple[float, float], logs: list[dict]) -> None:
    """Strong lasers do not stop learning: the reconstruction error on a fixed, dazzled validation batch falls
    (measured after / before: rec1 0.60-0.64, rec2 0.33 after 60 steps; G1's output starts at the sensor image
    through its global skip, so rec1 falls least) and the critics settle (median critic loss
    of the second half / of the first 10 steps: 0.15 after 60 steps, 0.07 after 300; single GP spikes of a few
    hundred are normal and recover within a few steps, hence medians)."""
    after = validation_rec(tr)
    assert learning_ratio(before, after) < LEARNING_RATIO, (before, after)
    crit = [t["critic_total"] for t in logs]
    assert statistics.median(crit[len(crit) // 2:]) < 0.5 * statistics.median(crit[:10])


def _weights_finite(modules) -> bool:
    return all(bool(torch.isfinite(p).all()) for m in modules for p in m.parameters())


@pytest.mark.parametrize("steps", [pytest.param(60, id="ci"), pytest.param(600, marks=pytest.mark.slow, id="long")])
def test_long_wgan_gp_run_under_strong_lasers_stays_finite_bounded_and_learns(tmp_path, steps):
    tr = tiny_trainer(tmp_path, *STRONG_LASER, steps=steps, **NO_IO)
    assert tr.model.weights.adv > 0 and tr.model.weights.gp > 0  # SGAN-B: WGAN-GP critics D1 and D2 (two scales)
    before = validation_rec(tr)
    saturated = _record_saturation(tr)
    logs = _train(tr, steps)
    assert tr.step == steps and tr.skipped == 0
    assert all(s > 0 for s in saturated)  # the laser saturated pixels in every batch
    _check_finite_and_bounded(logs)
    _check_learning(tr, before, logs)
    assert _weights_finite([tr.model])


@pytest.mark.parametrize("steps", [pytest.param(24, id="ci"), pytest.param(300, marks=pytest.mark.slow, id="long")])
def test_bf16_autocast_run_under_strong_lasers_stays_finite_and_bounded(tmp_path, steps):
    """trainer.amp=bf16: the networks in bfloat16, the optics, the simulation, the Wiener layer and the losses in
    float32 (docs/scaling.md): the same bounds as the float32 run, every batch saturated by the laser."""
    tr = tiny_trainer(tmp_path, *STRONG_LASER, steps=steps, amp="bf16", **NO_IO)
    saturated = _record_saturation(tr)
    logs = _train(tr, steps)
    assert tr.step == steps and tr.skipped == 0 and all(s > 0 for s in saturated)
    assert all(v.dtype == torch.float32 for t in logs for v in t.values())
    _check_finite_and_bounded(logs)
    assert _weights_finite([tr.model])


def _state(opt) -> dict:
    return copy.deepcopy(opt.state_dict()["state"])


def _same_state(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[i][k], b[i][k]) for i in a for k in a[i])


def _snapshot(modules) -> list[torch.Tensor]:
    return [p.detach().clone() for m in modules for p in m.parameters()]


def _same(a, b) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a, b))


NAN_STEP_TOL = 0.0  # a step whose critic loss is NaN leaves the critics and their Adam moments bit-identical


def _critic_state(tr) -> list[torch.Tensor]:
    return _snapshot(tr.model.critics()) + [v.clone() for s in tr.opt_d.state.values() for v in s.values()]


def nan_penalty_step(tr) -> tuple[dict, float]:
    """One training step with a NaN gradient penalty (the critic's double backward). Returns (its logged terms, the
    largest change of any critic weight or critic Adam moment over it: 0 when the critic update was skipped;
    inf if the step did not report the skip or the optimizer state changed shape)."""
    before, gp = _critic_state(tr), losses.gradient_penalty
    losses.gradient_penalty = lambda *a, **k: gp(*a, **k) * float("nan")
    try:
        terms = tr.train_step()
    finally:
        losses.gradient_penalty = gp
    after = _critic_state(tr)
    if terms.get("critic_skipped") != 1.0 or len(before) != len(after) or \
            any(x.shape != y.shape for x, y in zip(before, after)):
        return terms, math.inf
    changes = [float((x - y).abs().max()) for x, y in zip(before, after) if x.numel()]
    return terms, math.nan if any(math.isnan(c) for c in changes) else max(changes, default=0.0)


def test_forced_nans_mid_run_skip_only_the_poisoned_update_and_training_recovers(tmp_path, caplog):
    tr = tiny_trainer(tmp_path, *STRONG_LASER, steps=40, ema=0.99, **NO_IO)
    gens, crits = tr.model.generators(), tr.model.critics()
    logs = _train(tr, 10)

    def before():
        return (_snapshot(gens), _snapshot(crits), _state(tr.opt_g), _state(tr.opt_d),
                _snapshot(tr.ema.shadow))

    # 1. NaN gradient penalty (the critic's double backward): the critic update is skipped, the generator's not
    g0, d0, sg0, sd0, e0 = before()
    with caplog.at_level(logging.WARNING, logger="codesign.train"):
        terms, change = nan_penalty_step(tr)
        tr.guard.report(tr.step)
    assert terms["critic_skipped"] == 1.0 and math.isnan(terms["critic_total"]) and tr.skipped == 1
    assert "step 11: 1 update(s) skipped since the last report (1 non-finite loss, 0 non-finite gradient)" \
        in caplog.text
    assert _same(d0, _snapshot(crits)) and _same_state(sd0, _state(tr.opt_d))
    assert change <= NAN_STEP_TOL  # the same, as one number (a NaN fails too)
    assert not _same(g0, _snapshot(gens)) and not _same(e0, _snapshot(tr.ema.shadow))
    assert math.isfinite(terms["generator_total"]) and terms["generator_skipped"] == 0.0
    logs += [terms] + _train(tr, 4)

    # 2. Inf in one generator gradient: the generator update (and its EMA) is skipped, the critics' is not
    caplog.clear()
    g0, d0, sg0, sd0, e0 = before()
    hook = next(tr.model.g2.parameters()).register_hook(lambda g: torch.full_like(g, float("inf")))
    with caplog.at_level(logging.WARNING, logger="codesign.train"):
        terms = tr.train_step()
        tr.guard.report(tr.step)
    hook.remove()
    assert terms["generator_skipped"] == 1.0 and terms["critic_skipped"] == 0.0 and tr.skipped == 2
    assert "step 16: 1 update(s) skipped since the last report (0 non-finite loss, 1 non-finite gradient)" \
        in caplog.text
    assert _same(g0, _snapshot(gens)) and _same_state(sg0, _state(tr.opt_g)) and _same(e0, _snapshot(tr.ema.shadow))
    assert not _same(d0, _snapshot(crits))
    logs += [terms] + _train(tr, 4)

    # 3. a NaN pixel in a simulated batch (e.g. an overflow at the laser spot): both updates skipped
    caplog.clear()
    g0, d0, sg0, sd0, e0 = before()
    draw = tr.data.train_batch

    def corrupted(step):
        batch = draw(step)
        batch["sensor"][0, 0, 20, 20] = float("nan")
        return batch

    tr.data.train_batch = corrupted
    terms = tr.train_step()
    tr.data.train_batch = draw
    assert terms["generator_skipped"] == terms["critic_skipped"] == 1.0 and tr.skipped == 4
    assert _same(g0, _snapshot(gens)) and _same(d0, _snapshot(crits)) and _same(e0, _snapshot(tr.ema.shadow))
    assert _same_state(sg0, _state(tr.opt_g)) and _same_state(sd0, _state(tr.opt_d))

    # ... and the run goes on: every later step is finite, bounded and updates both sides
    after = _train(tr, 40 - tr.step)
    assert tr.step == 40 and tr.skipped == 4
    assert all(float(t[k]) == 0.0 for t in after for k in t if k.endswith("_skipped"))
    _check_finite_and_bounded(logs[:10] + logs[11:] + after)  # all but the NaN critic loss of step 10
    assert _weights_finite([tr.model] + tr.ema.shadow)


def _joint_trainer(tmp_path: Path, steps: int):
    """The co-design trainer on the strong-laser data, mask trainable from step 0, the published mask's smooth
    LSR as the ceiling (what +experiment=joint does with codesign.lsr_max = null), with the paper's SGAN-B, the
    network the learning figures of _check_learning were measured with (the main job's gated SGAN-B, its default
    since, lets G1's validation rec1 rise over 80 steps, 0.0133 -> 0.0171, while rec2 falls 0.41 -> 0.23: G1's
    learned correction starts below its classical base, docs/models.md Sec. 10)."""
    return joint_trainer(tmp_path, *STRONG_LASER, "model=sgan_b", steps=steps)


@pytest.mark.parametrize("steps", [pytest.param(12, id="ci"), pytest.param(80, marks=pytest.mark.slow, id="long")])
def test_joint_mask_and_network_under_strong_lasers_stay_finite_and_feasible(tmp_path, steps):
    tr = _joint_trainer(tmp_path, steps)
    cs, limit = tr.codesign.spec, tr.codesign.constraint.lsr_max * (1 + tr.codesign.spec.guard_tolerance)
    # the guard keeps smooth LSR <= lsr_max (1 + tol) after every update, so the penalty w relu(LSR / lsr_max -
    # (1 - margin))^2 can never exceed w (margin + tol)^2 (= 4 at the start, where the mask is the published one);
    # 1e-3 relative slack for the float32 PSF [measured max 4.000]
    penalty_max = cs.penalty_weight * (cs.margin + cs.guard_tolerance) ** 2 * (1 + 1e-3)
    start, initial, logs, lsrs = snapshot(tr.codesign.mask), copy.deepcopy(tr.model.state_dict()), [], []
    for _ in range(steps):
        logs.append(tr.train_step())
        lsrs.append(tr.codesign.constraint.measure(tr.codesign.mask))
        assert lsrs[-1] <= limit and lsrs[-1] == pytest.approx(tr.codesign.lsr, rel=1e-6)
    assert tr.skipped == 0 and tr.codesign.record()["mask_rollbacks"] == 0
    assert all("lsr_penalty" in t and 0 <= t["lsr_penalty"] <= penalty_max for t in logs)
    _check_finite_and_bounded(logs)
    if steps >= 40:  # too few steps in the CI variant to compare medians
        # learning is judged on one batch: the validation batch through the final mask, restored by the initial
        # and by the trained network (through the start mask the targets themselves differ: G1's target I_b and
        # the sensor image move with the mask; measured that way rec1 read 0.0133 -> 0.0171 while rec2 fell)
        trained = copy.deepcopy(tr.model.state_dict())
        tr.model.load_state_dict(initial)
        before = validation_rec(tr)
        tr.model.load_state_dict(trained)
        _check_learning(tr, before, logs)
    assert _weights_finite([tr.model, tr.codesign.mask])
    assert not all(torch.equal(a, b) for a, b in zip(start, snapshot(tr.codesign.mask)))  # the mask did move


def test_the_bound_check_lets_a_single_penalty_spike_pass_and_catches_a_diverging_critic():
    calm = {"d2_gp": 10.0, "critic_total": 100.0, "rec1": 0.1}
    spike = {"d2_gp": 8e4, "critic_total": 8e5, "rec1": 0.1}
    _check_finite_and_bounded([calm, spike, calm, calm])
    for logs in ([calm, spike, spike, spike, calm],  # no recovery within two steps
                 [calm, {**spike, "d2_gp": 2e6}, calm],  # beyond the cap
                 [calm, {**calm, "rec1": 6.0}],  # a non-penalty term is never allowed a spike
                 [calm, {**calm, "d2_gp": math.nan}]):
        with pytest.raises(AssertionError):
            _check_finite_and_bounded(logs)
