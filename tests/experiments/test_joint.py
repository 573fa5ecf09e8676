"""``+experiment=joint codesign.protocol=single debug=smoke`` end to end (one joint training and its published
comparison, each arm of the main job's protocol): metrics, figures, TensorBoard tags, and resume of a killed run.
The main job's whole protocol: tests/experiments/test_main_job.py."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from codesign.io.metric_names import upgrade
from tests.cli import run_codesign
from tests.conftest import REPO_ROOT as REPO

# the joint experiment's mechanics with the SGAN (the main job's network is wiener_naf, whose co-design
# tests/models/test_wiener_naf.py covers): its two generators, its fixed image size, its named loss terms
SINGLE = "codesign.protocol=single"
SGAN = "model=sgan_b_l1"
KEYS = ("lsr", "lsr_published", "mtf_mean", "mtf_mean_published", "psnr", "psnr_published", "ssim", "ssim_published",
        "r_n", "theta_n", "steps", "seconds", "lsr_max", "psnr_laser_1e6", "psnr_published_laser_1e6",
        "psnr_laser_0", "ssim_published_laser_0", "diverged", "diverged_published", "phase_resolved",
        "phase_resolved_start", "lsr_smooth_start", "lsr_max_over_start", "lsr_max_reachable")


def _tags(run_dir: Path) -> dict:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir), size_guidance={"scalars": 0, "images": 0, "histograms": 0})
    acc.Reload()
    return acc.Tags()


@pytest.fixture(scope="module")
def joint_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("joint") / "run"
    proc = run_codesign("+experiment=joint", SINGLE, SGAN, "debug=smoke", f"hydra.run.dir={run_dir}", timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    (run_dir.parent / "console.txt").write_text(proc.stdout + proc.stderr)
    return run_dir


def test_joint_writes_the_comparison_metrics(joint_run):
    m = json.loads((joint_run / "metrics.json").read_text())
    for k in KEYS:
        assert k in m, k
    assert m["steps"] == 4 and len(m["r_n"]) == 5 and len(m["theta_n"]) == 5
    assert m["lsr_constraint_met"] is True and m["lsr_smooth"] <= m["lsr_max"] * (1 + 1e-6)
    assert m["lsr_max"] == pytest.approx(m["lsr_smooth_published"], rel=1e-6)  # default: the published mask's
    assert set(m["evaluation"]) == set(m["evaluation_published"]) == {"laser_0", "laser_1e6", "H1"}
    assert m["evaluation_scenes"] == ["awning.png", "bridge_city.png"]  # the shipped held-out photographs
    assert upgrade(m)[1] == {}  # every key under today's name (codesign.io.metric_names)
    learned = json.loads((joint_run / "learned_mask.json").read_text())
    assert learned["kind"] == "halfring" and learned["r"] == m["r_n"]
    for name in ("checkpoint.pt", "mtf.png", "compare_laser_1e6.png", "learned_phase.png", "learned_psf_log.png",
                 "published_phase.png", "evaluation.csv", "published/checkpoint.pt", "published/metrics.json",
                 "published/evaluation.csv"):
        assert (joint_run / name).is_file(), name


def test_joint_ends_with_the_summary_and_its_verdict(joint_run):
    console = (joint_run.parent / "console.txt").read_text()
    m = json.loads((joint_run / "metrics.json").read_text())
    summary = console[console.index("== summary: 4 steps, seed 0, 2 held-out test scene(s) =="):]
    assert f"{'learned':<11}{m['lsr']:>10.3e}{m['mtf_mean']:>10.4f}" in summary
    assert f"{'published':<11}{m['lsr_published']:>10.3e}" in summary
    row = m["evaluation_published"]["laser_1e6"]["sensor"]["psnr_matched"]
    assert "  floor: sensor image (published)" in summary and f"{row:>8.2f}" in summary
    per = m["evaluation_per_scene_psnr_matched"]["laser_1e6"]["sgan"]
    assert len(per) == 2 and sum(per) / 2 == pytest.approx(m["evaluation"]["laser_1e6"]["sgan"]["psnr_matched"])
    assert "verdict: the learned mask lets" in summary and "(2 scenes; 95 % interval of the per-scene" in summary
    assert m["network"] == "sgan_b_l1" and "learned mask + sgan_b_l1" in summary  # the configured name
    r = m["recheck"]
    assert r["learned"]["fine"]["pupil_n"] > r["learned"]["design"]["pupil_n"]
    assert r["published"]["whole"]["focal_n"] == 2 * r["published"]["design"]["focal_n"]
    assert r["lsr_ratio_design"] == pytest.approx(r["learned"]["design"]["lsr"] / r["published"]["design"]["lsr"])
    assert f"the gain moves by {100 * m['recheck_gain_moved']:.1f} %" in summary
    # the first progress line's ETA covers the published training too: twice the joint steps left, about
    first = next(line for line in console.splitlines() if "step 1/4" in line)
    rate, eta = (float(x) for x in re.search(r"([\d.]+) s/step\s+ETA (\d+) s", first).groups())
    assert eta == pytest.approx(rate * 7, abs=1)


def test_joint_tensorboard_holds_losses_mask_constraint_images_and_hparams(joint_run):
    tags = _tags(joint_run)
    for t in ("loss/generator_total", "loss/lsr_penalty", "constraint/lsr_smooth", "constraint/lsr_max",
              "mask/mtf_mean", "mask/lsr_smooth_gap", "mask_params/r_1", "mask_params/theta_5",
              "lr/generator_mask", "wiener/gamma_mean", "val/psnr", "val/ssim"):
        assert t in tags["scalars"], t
    for t in ("mask/phase", "mask/psf_log10", "mask/mtf2d_log10", "mask/mtf_curve", "images/sensor_input",
              "images/restored_b", "images/ground_truth_b"):
        assert t in tags["images"], t
    assert "mask_params/r" in tags["histograms"] and "mask_params/theta" in tags["histograms"]
    assert "loss/generator_total" in _tags(joint_run / "published")["scalars"]
    assert any((joint_run / "hparams").iterdir())


@pytest.mark.slow  # 25 s: a killed and a resumed process; twins: test_seeded_runs_reproduce_and_resume_continues_exactly, test_resumed_seconds_count_the_checkpoints
def test_a_run_killed_at_a_step_and_resumed_records_what_an_uninterrupted_run_records(joint_run, tmp_path):
    """SIGKILL right after the joint training's checkpoint at step 2 of 4, then the same command again: every
    value of metrics.json equals the uninterrupted run's (the same command in joint_run), the untrained network's
    *_start scores included, but the wall times; seconds counts the whole training, not the part after the resume."""
    run_dir = tmp_path / "run"
    killer = [sys.executable, str(Path(__file__).with_name("kill_after_checkpoint.py")), "1", "+experiment=joint",
              SINGLE, SGAN, "debug=smoke", f"hydra.run.dir={run_dir}"]
    killed = subprocess.run(killer, cwd=REPO, capture_output=True, text=True, timeout=300,
                            env={**os.environ, "OMP_NUM_THREADS": "2", "MKL_NUM_THREADS": "2"})
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-3000:]
    assert not (run_dir / "metrics.json").exists() and (run_dir / "checkpoint.pt").is_file()
    # the training seconds before the kill, as the checkpoint holds them, made large: the resumed run's seconds must
    # count them (the whole training's), not restart from the resume
    state = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    state["seconds"] = 1.0e6
    torch.save(state, run_dir / "checkpoint.pt")
    again = run_codesign("+experiment=joint", SINGLE, SGAN, "debug=smoke", f"hydra.run.dir={run_dir}", timeout=300)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "at step 2" in again.stdout + again.stderr
    resumed = json.loads((run_dir / "metrics.json").read_text())
    whole = json.loads((joint_run / "metrics.json").read_text())
    assert resumed.keys() == whole.keys()
    timing = {"seconds", "seconds_published", "checkpoint"}
    assert [k for k in whole if k not in timing and resumed[k] != whole[k]] == []
    assert 1.0e6 < resumed["seconds"] < 1.0e6 + 300  # the whole training's, not the 2 steps after the resume
    # the same run directory under a changed constraint is refused, naming the key
    bad = run_codesign("+experiment=joint", SINGLE, SGAN, "debug=smoke", "trainer.steps=6", "codesign.lsr_max=0.001",
                       f"hydra.run.dir={run_dir}", timeout=300)
    assert bad.returncode == 2 and "was trained with different codesign" in bad.stderr


def test_evaluate_of_a_joint_checkpoint_uses_the_learned_mask(joint_run, tmp_path):
    proc = run_codesign("+experiment=evaluate", f"checkpoint={joint_run / 'checkpoint.pt'}", "debug=smoke",
                        f"hydra.run.dir={tmp_path / 'eval'}", timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    ev = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    joint = json.loads((joint_run / "metrics.json").read_text())
    assert ev["evaluation"] == joint["evaluation"]  # the learned mask's sensor images, not the published mask's
    assert ev["evaluation"] != joint["evaluation_published"]


def test_warm_start_frozen_mask_continues_the_checkpoint_exactly(joint_run, tmp_path):
    """init.checkpoint with the published network (trained 4 steps on the published mask) and the mask frozen
    (codesign.mask_lr=0, the control arm of a fine-tuning study): the untrained-network validation scores of the
    new run are the checkpoint's final ones, bit for bit; the mask does not move; the start is recorded."""
    ckpt = joint_run / "published" / "checkpoint.pt"
    run_dir = tmp_path / "warm"
    proc = run_codesign("+experiment=joint", SINGLE, SGAN, "debug=smoke", f"init.checkpoint={ckpt}",
                        "codesign.mask_lr=0",
                        "codesign.lsr_max=start", "codesign.compare_published=false", "logging.tensorboard=false",
                        f"hydra.run.dir={run_dir}", timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    m = json.loads((run_dir / "metrics.json").read_text())
    pretrained = json.loads((joint_run / "published" / "metrics.json").read_text())
    assert m["val_psnr_start"] == pretrained["val_psnr_end"] and m["val_ssim_start"] == pretrained["val_ssim_end"]
    assert m["init_checkpoint"] == str(ckpt) and m["init_steps"] == 4 and m["init_mask_kind"] == "halfring"
    assert m["lsr"] == m["lsr_published"]  # the frozen start mask is the published one
    assert m["lsr_max_from"] == "the start mask's smooth LSR"
    assert m["lsr_max"] == pytest.approx(m["lsr_smooth_published"], rel=1e-6)  # the start is the published mask


def test_warm_start_from_other_image_sizes_is_refused_before_work(joint_run, tmp_path, monkeypatch, capsys):
    from tests.inputs._run import config_error

    ckpt = joint_run / "published" / "checkpoint.pt"
    line = config_error(monkeypatch, capsys, tmp_path / "bad", "+experiment=joint", SGAN, "debug=smoke",
                        f"init.checkpoint={ckpt}", "data.image_size=64", "data.padded_size=96")
    assert line == (
        f"codesign: configuration error: init.checkpoint = '{ckpt}': was trained with different data.image_size, "
        "data.padded_size (data.image_size = 96 there, 64 here; data.padded_size = 128 there, 96 here): a warm start "
        "keeps the network, the optics, the sensor and the image sizes (only the mask may change)")
    assert not (tmp_path / "bad" / "checkpoint.pt").exists()
