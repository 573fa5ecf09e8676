"""Physically meaningless settings say so (issue 16 item 6): a phase the pupil grid cannot resolve, a
codesign.lsr_max no mask can reach or far below the start, and a training run whose losses diverge."""
from __future__ import annotations

import json
import logging
import math

import pytest
import torch

from codesign.camera.build import build_camera
from codesign.design.check import phase_sampling
from codesign.design.limits import MTFLimit
from codesign.train.lsr_constraint import CodesignSpec
from codesign.design.merit import MaskMonitor, MetricsSpec, published_reference
from codesign.experiments import joint
from codesign.experiments.specs import metrics_spec
from tests.cli import run_codesign
from tests.inputs._run import compose_cfg
from tests.train._util import tiny_trainer

FAST_RING = ["mask.preset=null", "mask.r=[1e4,91.8,6.3,10.3,4.2]", "mask.theta=[1.86,1.09,1.15,1.21,1.22]"]


def _camera(*overrides):
    cfg = compose_cfg("+experiment=psf", *overrides)
    return cfg, build_camera(cfg, torch.device("cpu"))


def test_the_published_phase_is_resolved_and_a_ring_of_1e4_is_not():
    for overrides, resolved in (((), True), (FAST_RING, False)):
        cfg, cam = _camera(*overrides)
        check = phase_sampling(cam.mask, cam.system.spec, metrics_spec(cfg).mtf_band)
        assert check["resolved"] is resolved
        assert check["pupil_n"] == 402 and check["fine_pupil_n"] == 800
    # the aliased mask's "low LSR" is the sampling's: on the finer grid most of its light leaves the window
    assert check["window_energy_fine_deviation"] < -0.5 and check["lsr_fine_deviation"] < -0.3


def test_psf_flags_an_unresolved_phase_in_metrics_and_on_the_console(tmp_path):
    proc = run_codesign("+experiment=psf", *FAST_RING, f"hydra.run.dir={tmp_path / 'run'}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    log = proc.stdout + proc.stderr
    assert "halfring mask: the pupil grid (402 samples) does NOT resolve its phase: on a grid of 800 samples" in log
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["phase_resolved"] is False and m["phase_sampling"]["max_deviation"] > 0.5
    assert json.loads((tmp_path / "run" / "mask.json").read_text())["phase_resolved"] is False


def _lsr_max_setup():
    cfg, cam = _camera("optics.pupil_pitch_m=2.0e-5", "optics.focal_n=160")
    system = cam.system
    monitor = MaskMonitor(system, published_reference(dict(cfg.mask), system), (0.0, 0.5), MetricsSpec.lsr_p)
    return CodesignSpec.from_config({}), monitor, system, cam.mask


def test_an_unreachable_lsr_max_warns_at_the_start(caplog):
    cs, monitor, system, mask = _lsr_max_setup()
    with caplog.at_level(logging.WARNING, logger="codesign"):
        out = joint._check_lsr_max(1e-12, cs, monitor, system, mask)
    assert out["lsr_max_reachable"] is False and out["lsr_max_over_start"] < 1e-6
    assert "is below what any phase-only mask can reach on this 160-sample window" in caplog.text
    caplog.clear()
    start = out["lsr_smooth_start"]
    with caplog.at_level(logging.WARNING, logger="codesign"):
        far = joint._check_lsr_max(start / 12, cs, monitor, system, mask)
    assert far["lsr_max_reachable"] is True
    assert "is 12x below the start mask's smooth LSR" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="codesign"):
        joint._check_lsr_max(start, cs, monitor, system, mask)
    assert caplog.text == ""


def test_the_lsr_floor_is_the_light_spread_evenly_over_the_window():
    cs, monitor, system, mask = _lsr_max_setup()
    limit = MTFLimit(system, monitor.band)
    # a PSF of energy 1 spread evenly over m^2 samples has peak 1 / m^2: LSR = 1 / (m^2 h0(0))
    assert limit.lsr_limit(0.0) == pytest.approx(1.0 / (system.spec.focal_n ** 2 * limit.h0), rel=1e-9)


def test_a_diverging_training_is_flagged_and_warned(tmp_path, caplog):
    tr = tiny_trainer(tmp_path, "trainer.lr_weights=1", "trainer.lr_biases=1", steps=10, val_every=0,
                      checkpoint_every=0, image_every=0)
    with caplog.at_level(logging.WARNING, logger="codesign"):
        tr.fit(progress_every=1)
    d = tr.divergence()
    assert d["diverged"] == 1 and d["loss_growth"] > 100 and d["loss_growth_term"] in ("rec1", "rec2")
    assert "training DIVERGED: the reconstruction term" in caplog.text


def test_a_sound_training_is_not_flagged(tmp_path):
    tr = tiny_trainer(tmp_path, steps=6, val_every=0, checkpoint_every=0, image_every=0)
    tr.fit(progress_every=1)
    d = tr.divergence()
    assert d["diverged"] == 0 and 1.0 <= d["loss_growth"] < 10 and math.isfinite(d["loss_growth"])
