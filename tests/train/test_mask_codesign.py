"""Co-design: gradients reach the mask, the LSR constraint holds, NaN guards, reproducibility and resume."""
from __future__ import annotations

import logging

import pytest
import torch

from codesign.train.gan_update import GANUpdate
from codesign.train.lsr_constraint import CodesignSpec, LSRConstraint, snapshot
from codesign.errors import ConfigError
from tests.train._util import joint_trainer


@pytest.mark.parametrize("mask", ["halfring", "freeform"])
def test_mask_gets_a_finite_nonzero_gradient_through_the_whole_pipeline(tmp_path, mask):
    tr = joint_trainer(tmp_path, f"mask={mask}")
    tr.data.camera.set_trainable(True)
    batch = tr.data.train_batch(0)
    assert batch["sensor"].requires_grad and batch["otf"].requires_grad and not batch["irradiance"].requires_grad
    from codesign.models import pyramid

    batch["targets"] = pyramid(batch["scene"])
    out = tr.model(batch["sensor"], batch["otf"])
    terms = tr.update.generator_losses(batch, out)
    # the restoration loss alone (no LSR penalty) must move the mask
    (terms["generator_total"] - terms["lsr_penalty"]).backward()
    for name, p in tr.codesign.mask.named_parameters():
        assert p.grad is not None, name
        assert bool(torch.isfinite(p.grad).all()), name
        assert float(p.grad.abs().max()) > 0, name


def test_warmup_keeps_the_mask_out_of_the_graph(tmp_path):
    tr = joint_trainer(tmp_path, warmup_fraction=0.5)
    before = snapshot(tr.codesign.mask)
    tr.train_step()
    tr.train_step()
    assert all(torch.equal(a, b) for a, b in zip(before, snapshot(tr.codesign.mask)))
    assert tr.opt_g.param_groups[2]["lr"] == pytest.approx(tr.codesign.spec.mask_lr)  # active from step 2 of 4
    tr.train_step()
    assert not all(torch.equal(a, b) for a, b in zip(before, snapshot(tr.codesign.mask)))


def large_mask_step_trainer(tmp_path, steps: int = 4):
    """The co-design trainer with a mask step 25x the default and no penalty: only the feasibility guard keeps
    smooth LSR <= lsr_max."""
    return joint_trainer(tmp_path, steps=steps, mask_lr=0.5, penalty_weight=0.0)


def guard_limit(tr) -> float:
    """The largest smooth LSR / lsr_max the guard lets an update end at: 1 + codesign.guard_tolerance."""
    return 1 + tr.codesign.spec.guard_tolerance


def lsr_ratios(tr, steps: int) -> list[float]:
    """Trains ``steps`` steps; smooth LSR of the mask / lsr_max after each."""
    ratios = []
    for _ in range(steps):
        tr.train_step()
        ratios.append(tr.codesign.constraint.measure(tr.codesign.mask) / tr.codesign.constraint.lsr_max)
    return ratios


def test_learned_mask_never_ends_above_lsr_max_under_a_large_mask_step(tmp_path):
    # a mask step 25x the default with no penalty: only the guard keeps the constraint
    tr = large_mask_step_trainer(tmp_path)
    for k, ratio in enumerate(lsr_ratios(tr, 4)):  # benchmarks/bench_accuracy.py reports the largest ratio
        assert ratio <= guard_limit(tr), f"step {k}: smooth LSR / lsr_max = {ratio!r}"
    assert tr.codesign.lsr == pytest.approx(tr.codesign.constraint.measure(tr.codesign.mask), rel=1e-6)


def test_guard_shortens_a_violating_update_and_an_infeasible_start_only_descends(tmp_path):
    tr = joint_trainer(tmp_path)
    c, mask = tr.codesign.constraint, tr.codesign.mask
    start, lsr0 = snapshot(mask), c.measure(mask)
    # a tight ceiling (start infeasible): a random large move may only be kept where it lowers the LSR
    tight = LSRConstraint(tr.codesign.spec, tr.data.camera.system, 0.5 * lsr0, tr.codesign.constraint.p)
    gen = torch.Generator().manual_seed(3)
    lsr = lsr0
    for _ in range(6):
        prev = snapshot(mask)
        with torch.no_grad():
            for p in mask.parameters():
                p.add_(3.0 * torch.randn(p.shape, generator=gen, dtype=p.dtype))
        lsr_new, kept = tight.enforce(mask, prev, lsr)
        assert lsr_new <= lsr * (1 + 1e-6) and 0.0 <= kept <= 1.0
        assert lsr_new == pytest.approx(tight.measure(mask), rel=1e-6)
        lsr = lsr_new
    assert tight.shortened + tight.undone >= 1
    # feasible start, ceiling = its LSR: any update ends at or below it
    c2 = LSRConstraint(tr.codesign.spec, tr.data.camera.system, lsr0, tr.codesign.constraint.p)
    from codesign.train.lsr_constraint import restore

    restore(mask, start)
    with torch.no_grad():
        mask.r.add_(torch.tensor([0.0, -40.0, 0.0, 0.0, 0.0], dtype=mask.r.dtype))
    lsr_new, _ = c2.enforce(mask, start, lsr0)
    assert lsr_new <= lsr0 * (1 + 1e-6)


def test_peak_guard_keeps_the_certified_peak_where_the_smooth_lsr_alone_lets_it_rise(tmp_path):
    """codesign.peak_max: with the smooth ceiling wide open, random large moves raise the certified peak; with the
    peak guard every kept move ends with a certified peak at or below max(peak_max, the peak before it), the guard's
    record being the certified peak of the parameters it kept."""
    from codesign.train.lsr_constraint import restore

    tr = joint_trainer(tmp_path)
    mask, system, spec = tr.codesign.mask, tr.data.camera.system, tr.codesign.spec
    start = snapshot(mask)
    open_smooth = LSRConstraint(spec, system, 1.0, tr.codesign.constraint.p)
    peak0 = open_smooth.measure_peak(mask)
    moves = [3.0 * torch.randn(p.shape, generator=torch.Generator().manual_seed(5 + k), dtype=p.dtype)
             for k, p in enumerate(mask.parameters())]

    def move(constraint) -> float:
        restore(mask, start)
        prev = snapshot(mask)
        with torch.no_grad():
            for p, d in zip(mask.parameters(), moves):
                p.add_(d)
        constraint.enforce(mask, prev, 1.0)  # the smooth ceiling (1.0) never binds
        return constraint.measure_peak(mask)

    assert move(open_smooth) > 1.05 * peak0  # without the guard this move raises the peak
    guarded = LSRConstraint(spec.replace(peak_max=peak0), system, 1.0, tr.codesign.constraint.p)
    guarded.peak = peak0
    after = move(guarded)
    assert after <= peak0 * (1 + spec.guard_tolerance)
    assert guarded.shortened + guarded.undone == 1
    assert guarded.peak == pytest.approx(after if guarded.shortened else peak0, rel=1e-9)


def test_lsr_max_as_a_share_of_the_published_mask():
    from codesign.train.lsr_constraint import published_fraction

    assert published_fraction("published") == 1.0 and published_fraction("published/4") == 0.25
    assert [published_fraction(v) for v in ("published/1", "published/x", "published/inf", "start", 0.5)] == \
        [None] * 5


def test_lsr_max_becomes_a_number_in_one_place():
    """CodesignSpec.lsr_max_value: what each protocol's ceiling is and what metrics.json says it came from; only the
    mask the setting names is measured."""
    def never():
        raise AssertionError("measured a mask the setting does not name")

    peak = lambda: 2e-3  # noqa: E731
    value = lambda v, **kw: CodesignSpec(lsr_max=v).lsr_max_value(**kw)  # noqa: E731
    assert value(0.5, published=never, start=never) == (0.5, "given")
    assert value("published", published=peak) == (2e-3, "the published mask's smooth LSR")
    assert value("published/8", published=peak, measure="certified peak") == \
        (0.125 * 2e-3, "1/8 of the published mask's certified peak")
    assert value(None, published=peak, measure="certified peak", default_share=0.25) == \
        (0.25 * 2e-3, "1/4 of the published mask's certified peak")
    assert value("start", published=never, start=lambda: 3e-3) == (3e-3, "the start mask's smooth LSR")
    assert value("start", published=peak, measure="certified peak") == (2e-3, "the published mask's certified peak")


def test_penalty_is_zero_inside_the_margin_and_quadratic_beyond(tmp_path):
    tr = joint_trainer(tmp_path)
    c = tr.codesign.constraint
    m = c.lsr_max
    assert float(c.penalty(torch.tensor(0.97 * m))) == 0.0
    expected = tr.codesign.spec.penalty_weight * (1.1 - (1 - tr.codesign.spec.margin)) ** 2
    assert float(c.penalty(torch.tensor(1.1 * m, dtype=torch.float64))) == pytest.approx(expected, rel=1e-9)


def test_nan_loss_skips_the_step_and_leaves_mask_and_network_untouched(tmp_path, caplog, monkeypatch):
    tr = joint_trainer(tmp_path, "model=sgan_b_l1")  # the SGAN's update poisoned (GANUpdate, its G1)
    tr.train_step()
    mask_before = snapshot(tr.codesign.mask)
    net_before = [p.detach().clone() for p in tr.model.g1.parameters()]
    orig = GANUpdate.generator_losses

    def poisoned(self, batch, out):
        terms = orig(self, batch, out)
        terms["generator_total"] = terms["generator_total"] * float("nan")
        return terms

    monkeypatch.setattr(GANUpdate, "generator_losses", poisoned)
    with caplog.at_level(logging.WARNING, logger="codesign.train"):
        terms = tr.train_step()
        tr.guard.report(tr.step)
    assert terms["generator_skipped"] == 1.0 and tr.skipped == 1
    assert "(1 non-finite loss, 0 non-finite gradient)" in caplog.text
    assert all(torch.equal(a, b) for a, b in zip(mask_before, snapshot(tr.codesign.mask)))
    assert all(torch.equal(a, b) for a, b in zip(net_before, tr.model.g1.parameters()))


def test_nan_mask_gradient_skips_and_nan_mask_after_update_restores_the_last_good_mask(tmp_path, caplog,
                                                                                       monkeypatch):
    tr = joint_trainer(tmp_path)
    tr.train_step()
    good = snapshot(tr.codesign.mask)
    hook = tr.codesign.mask.r.register_hook(lambda g: g * float("inf"))
    with caplog.at_level(logging.WARNING, logger="codesign.train"):
        terms = tr.train_step()
        tr.guard.report(tr.step)
    hook.remove()
    assert terms["generator_skipped"] == 1.0 and "(0 non-finite loss, 1 non-finite gradient)" in caplog.text
    assert all(torch.equal(a, b) for a, b in zip(good, snapshot(tr.codesign.mask)))
    # an update that leaves NaN in the mask (e.g. a corrupted optimizer state): rolled back
    orig_step = tr.opt_g.step

    def corrupt(*a, **k):
        out = orig_step(*a, **k)
        with torch.no_grad():
            tr.codesign.mask.theta[0] = float("nan")
        return out

    monkeypatch.setattr(tr.opt_g, "step", corrupt)
    before = snapshot(tr.codesign.mask)
    with caplog.at_level(logging.WARNING, logger="codesign.train"):
        terms = tr.train_step()
        tr.guard.report(tr.step)
    # the whole update (network and mask) is undone by the trainer, as a non-finite gradient's would be skipped
    assert tr.rollbacks == 1 and terms["generator_skipped"] == 1.0
    assert "1 update(s) left non-finite weights and were undone" in caplog.text
    assert all(torch.equal(a, b) for a, b in zip(before, snapshot(tr.codesign.mask)))


def _params(tr) -> list[torch.Tensor]:
    return [p.detach().clone() for p in tr.model.parameters()] + snapshot(tr.codesign.mask)


def test_seeded_runs_reproduce_and_resume_continues_exactly(tmp_path):
    # the far PSF's refresh schedule and source values travel in the checkpoint (a 640-pixel sensor: a small far plane)
    halo = ["sensor.laser_halo=true", "sensor.resolution=640"]
    a = joint_trainer(tmp_path / "a", *halo)
    for _ in range(4):
        a.train_step()
    b = joint_trainer(tmp_path / "b", *halo)
    for _ in range(4):
        b.train_step()
    for x, y in zip(_params(a), _params(b)):
        torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6)
    # resume: 2 steps, checkpoint, a fresh trainer loads it and does the other 2
    c = joint_trainer(tmp_path / "c", *halo)
    c.train_step()
    c.train_step()
    path = c.save()
    from codesign.train.checkpoint import load_checkpoint

    d = joint_trainer(tmp_path / "d", *halo, seed=5)  # different init: everything must come from the checkpoint
    d.load_state_dict(load_checkpoint(path))
    assert d.step == 2 and d.opt_g.param_groups[2]["lr"] == c.opt_g.param_groups[2]["lr"]
    d.train_step()
    d.train_step()
    for x, y in zip(_params(a), _params(d)):
        torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6)
    assert d.codesign.lsr == pytest.approx(a.codesign.lsr, rel=1e-5)


def test_codesign_settings_are_validated_with_the_key_named():
    with pytest.raises(ConfigError, match=r"codesign.mask_schedule = 'linear': must be one of"):
        CodesignSpec.from_config({"mask_schedule": "linear"})
    with pytest.raises(ConfigError, match=r"codesign.lsr_max = -0.1"):
        CodesignSpec.from_config({"lsr_max": -0.1})
    with pytest.raises(ConfigError, match=r"codesign.mtf_band"):
        CodesignSpec.from_config({"mtf_band": [0.5, 0.2]})
