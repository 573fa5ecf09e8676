"""``+experiment=baseline debug=smoke`` -> ``+experiment=evaluate`` -> ``+experiment=restore`` on real files."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.cli import run_codesign

METHODS = ("sensor", "wiener", "g1_wiener", "sgan")  # the SGAN has a G1 output: every baseline applies


def _run(*args: str):
    return run_codesign(*args, timeout=300)


@pytest.fixture(scope="module")
def baseline_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("baseline") / "run"
    proc = _run("+experiment=baseline", "debug=smoke", f"hydra.run.dir={run_dir}")
    assert proc.returncode == 0, proc.stderr[-4000:]
    return run_dir


def test_baseline_writes_checkpoint_metrics_tables_and_panels(baseline_run):
    for name in ("checkpoint.pt", "metrics.json", "evaluation.csv", "panel_laser_0.png", "panel_laser_1e6.png",
                 "panel_H1.png"):
        assert (baseline_run / name).is_file(), name
    m = json.loads((baseline_run / "metrics.json").read_text())
    assert m["steps"] == 4 and m["variant"] == "sgan_b" and m["skipped_updates"] == 0 and m["diverged"] == 0
    assert 0 < m["memory_estimate_gib"] < 4  # a smoke run's
    assert m["phase_resolved"] is False  # the smoke pupil grid (202 samples) does not resolve the published phase
    assert m["vgg_loss"] == "off: model.loss.vgg = 0 (not in this variant's objective)"  # SGAN-B has no VGG term
    assert m["perceptual_metrics"]["one_minus_lpips"].startswith("unavailable")
    assert m["perceptual_metrics"]["one_minus_dists"].startswith("unavailable")
    assert set(m["evaluation"]) == {"laser_0", "laser_1e6", "H1"}
    for cond, table in m["evaluation"].items():
        assert set(table) == set(METHODS)
        for method, row in table.items():
            assert 0 < row["psnr"] < 100 and -1 <= row["ssim"] <= 1 and 0 <= row["one_minus_mse"] <= 1
            assert row["psnr_matched"] >= row["psnr"] - 1e-4  # a per-image least-squares fit only lowers MSE
    assert m["psnr_sgan_laser_1e6"] == m["evaluation"]["laser_1e6"]["sgan"]["psnr"]
    rows = (baseline_run / "evaluation.csv").read_text().splitlines()
    assert rows[0].startswith("condition,method,one_minus_mse,psnr,ssim,ms_ssim") and len(rows) == 1 + 3 * 4


def test_tensorboard_has_losses_gamma_lr_validation_and_images(baseline_run):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(baseline_run), size_guidance={"images": 0, "scalars": 0})
    acc.Reload()
    scalars = set(acc.Tags()["scalars"])
    for tag in ("loss/rec1", "loss/rec2", "loss/adv", "loss/mdf", "loss/d1_gp", "loss/generator_total",
                "wiener/gamma_mean", "lr/generator_weights", "lr/critic_biases", "val/psnr", "val/ssim"):
        assert tag in scalars, tag
    # losses are read at logging steps only (logging.log_every = 10): the first and the last of the 4 steps
    assert [e.step for e in acc.Scalars("loss/rec1")] == [1, 4]
    images = set(acc.Tags()["images"])
    assert {"images/sensor_input", "images/pre_restored_i_b", "images/restored_b", "images/ground_truth_b"} <= images


def test_evaluate_from_checkpoint_reproduces_the_baseline_table(baseline_run, tmp_path):
    proc = _run("+experiment=evaluate", f"checkpoint={baseline_run / 'checkpoint.pt'}", "debug=smoke",
                f"hydra.run.dir={tmp_path / 'eval'}")
    assert proc.returncode == 0, proc.stderr[-4000:]
    ev = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    base = json.loads((baseline_run / "metrics.json").read_text())
    assert ev["evaluation"] == base["evaluation"]  # same seed, same checkpoint, same scenes: identical numbers


def test_the_readme_path_simulate_then_restore_works_as_written(baseline_run, tmp_path):
    """README: +experiment=simulate preset=cpu, then +experiment=restore input=<run>/captures (the CPU baseline's
    128 px; simulate's figures stay out of the captures folder)."""
    sim_dir = tmp_path / "sim"
    proc = _run("+experiment=simulate", "preset=cpu", "debug=smoke", f"hydra.run.dir={sim_dir}")
    assert proc.returncode == 0, proc.stderr[-4000:]
    inputs = sim_dir / "captures"
    assert sorted(p.suffix for p in inputs.iterdir()) == [".png", ".png"]
    out = tmp_path / "restore"
    proc = _run("+experiment=restore", f"input={inputs}", f"checkpoint={baseline_run / 'checkpoint.pt'}",
                f"hydra.run.dir={out}")
    assert proc.returncode == 0, proc.stderr[-4000:]
    restored = sorted(out.glob("restored_*.png"))
    assert len(restored) == 2
    for f in restored:
        img = np.asarray(Image.open(f))
        assert img.dtype == np.uint16 and img.shape == (128, 128)
    m = json.loads((out / "metrics.json").read_text())
    assert len(m["outputs"]) == 2 and m["image_size"] == 128


def test_a_rerun_under_another_model_is_refused_before_training(baseline_run, tmp_path, monkeypatch, capsys):
    """In process (the two processes of the slow test below): the resume check names the file and the key."""
    import shutil

    from tests.inputs._run import config_error

    copy = tmp_path / "again"
    shutil.copytree(baseline_run, copy)
    line = config_error(monkeypatch, capsys, copy, "+experiment=baseline", "debug=smoke", "model=sgan_f")
    assert f"trainer.resume = '{copy / 'checkpoint.pt'}': was trained with different model" in line
    assert (copy / "metrics.json").is_file()


@pytest.mark.slow  # 10 s: two more processes; twins: the test above, tests/train/test_trainer.py's resume tests
def test_rerun_in_the_same_dir_resumes_instead_of_retraining(baseline_run, tmp_path):
    import shutil

    copy = tmp_path / "again"
    shutil.copytree(baseline_run, copy)  # leave the module's run untouched for the other tests
    proc = _run("+experiment=baseline", "debug=smoke", f"hydra.run.dir={copy}")
    assert proc.returncode == 0, proc.stderr[-4000:]
    log = proc.stdout + proc.stderr  # Hydra's console log goes to stdout
    assert "resumed from" in log and "at step 4" in log
    assert "step 1/4" not in log
    proc = _run("+experiment=baseline", "debug=smoke", "model=sgan_f", f"hydra.run.dir={copy}")
    assert proc.returncode == 2  # a finished run is never rewritten under other settings (issue 59)
    assert f"hydra.run.dir = '{copy}': holds a finished +experiment=baseline run (" in proc.stderr
    assert "that was trained with different model." in proc.stderr
    assert (copy / "metrics.json").is_file()  # the refused run left the earlier results in place


def test_evaluate_without_checkpoint_is_a_config_error(tmp_path, monkeypatch, capsys):
    from tests.inputs._run import config_error

    line = config_error(monkeypatch, capsys, tmp_path / "e", "+experiment=evaluate")
    assert line.startswith("codesign: configuration error: checkpoint = None: give the trained model")
    assert not (tmp_path / "e").exists()


def test_evaluate_takes_the_scene_source_from_the_command_line_as_one():
    """Typing data.scenes=builtin for a checkpoint trained on a folder must not keep that folder (it would be
    refused: a folder is only read with data.scenes=folder); typing only data.folder keeps the checkpoint's
    scenes key, so the folder needs data.scenes=folder, as in every experiment."""
    from omegaconf import OmegaConf

    from codesign.experiments.evaluate import merged_eval_config

    ckpt = OmegaConf.create({"data": {"scenes": "folder", "folder": "/trained/on", "test_fraction": 0.2,
                                      "split_seed": 0, "cache_mb": 1.0}})
    cli = OmegaConf.create({"data": {"scenes": "builtin", "folder": None, "test_fraction": 0.5, "split_seed": 3,
                                     "cache_mb": 2.0}, "evaluate": {}})
    merged = merged_eval_config(cli, ckpt, frozenset({"data.scenes"}))
    assert (merged.data.scenes, merged.data.folder, merged.data.test_fraction) == ("builtin", None, 0.2)
    untouched = merged_eval_config(cli, ckpt, frozenset())
    assert (untouched.data.scenes, untouched.data.folder) == ("folder", "/trained/on")


def test_evaluate_refuses_a_model_other_than_the_checkpoints():
    from omegaconf import OmegaConf

    from codesign.errors import ConfigError
    from codesign.experiments.evaluate import refuse_other_model

    ckpt = OmegaConf.create({"model": {"kind": "sgan", "variant": "B", "size": "cpu"}})
    same = OmegaConf.create({"model": {"kind": "sgan", "variant": "B", "size": "cpu"}})
    other = OmegaConf.create({"model": {"kind": "sgan", "variant": "F", "size": "cpu"}})
    facts = {"kind": "sgan", "variant": "B", "size": "cpu"}
    refuse_other_model(other, ckpt, frozenset({"checkpoint"}), facts, "c.pt")  # not typed: the checkpoint's runs
    refuse_other_model(same, ckpt, frozenset({"model"}), facts, "c.pt")  # typed but the same model
    with pytest.raises(ConfigError) as info:
        refuse_other_model(other, ckpt, frozenset({"model"}), facts, "c.pt")
    assert str(info.value) == ("model = {'kind': 'sgan', 'variant': 'F', 'size': 'cpu'}: evaluate runs the model of "
                               "checkpoint c.pt (model.kind=sgan, variant=B, size=cpu): leave model and model.* off "
                               "the command line")
