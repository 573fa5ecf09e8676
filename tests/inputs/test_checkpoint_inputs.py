"""Checkpoints given to evaluate / restore / resume: every broken or foreign file is a ConfigError naming the key
and the file and saying what is wrong, never a torch unpickling or state-dict traceback."""
from __future__ import annotations

import copy
import re
from types import SimpleNamespace

import pytest
import torch
from omegaconf import OmegaConf

from codesign.errors import ConfigError
from codesign.train.checkpoint import save_checkpoint
from codesign.train.resume import apply_checkpoint_mask, load_trained
from codesign.experiments.resume import check_resume_config, resume_if_possible
from codesign.train.model_setup import build_model
from codesign.optics import OpticalSystem, OpticsSpec
from codesign.optics.masks import HalfRingMask
from tests.cli import run_codesign
from tests.train._util import tiny_cfg
from tests.inputs._run import config_error

CPU = torch.device("cpu")
FOREIGN = "; was it written by another configuration or version of codesign?"


def _save(tmp_path, state, name="ck.pt"):
    return save_checkpoint(tmp_path / name, state)


def _err(path, message):
    return "checkpoint = " + re.escape(repr(str(path))) + ": " + message


def test_a_good_checkpoint_loads(trained, tmp_path):
    model, generators, cfg, state = load_trained(_save(tmp_path, trained), CPU)
    assert model.spec.size == "tiny" and state["step"] == 4 and len(generators) == len(model.generators())


def test_truncated_checkpoint(trained, tmp_path):
    path = _save(tmp_path, trained)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # a copy cut short
    with pytest.raises(ConfigError, match=_err(path, r"is truncated or corrupt \(PytorchStreamReader failed reading "
                                                     r"zip archive: failed finding central directory\); copy it "
                                                     r"again, or use an earlier checkpoint$")):
        load_trained(path, CPU)


@pytest.mark.parametrize("content,message", [
    (b"", r"is empty \(0 bytes\): not a checkpoint \(an interrupted copy\?\)$"),
    (b"GIF89a" + bytes(range(256)) * 4, r"is not a torch checkpoint file \(it is neither a torch archive nor a "
                                        r"pickle\)$"),
], ids=["empty", "not-torch"])
def test_unreadable_files(tmp_path, content, message):
    path = tmp_path / "ck.pt"
    path.write_bytes(content)
    with pytest.raises(ConfigError, match=_err(path, message)):
        load_trained(path, CPU)


def test_pickled_objects_are_refused_unread(tmp_path):
    path = tmp_path / "ck.pt"
    torch.save({"model": {}, "config": SimpleNamespace(a=1)}, path)  # an arbitrary Python object inside
    with pytest.raises(ConfigError, match=_err(path, r"holds Python objects other than tensors and plain values: "
                                                     r"refused, since reading them could run code")):
        load_trained(path, CPU)


def test_folder_instead_of_file_points_at_the_checkpoint_inside(trained, tmp_path):
    _save(tmp_path, trained, "checkpoint.pt")
    with pytest.raises(ConfigError, match=_err(tmp_path, "is a folder, not a checkpoint file: give the file, e.g. "
                                                         + re.escape(f"checkpoint={tmp_path / 'checkpoint.pt'}"))):
        load_trained(tmp_path, CPU)


@pytest.mark.parametrize("drop,missing", [("step", "step"), ("config.mask", "config.mask")])
def test_incomplete_checkpoint(trained, tmp_path, drop, missing):
    state = copy.deepcopy(trained)
    if drop == "step":
        del state["step"]
    else:
        del state["config"]["mask"]
    path = _save(tmp_path, state)
    with pytest.raises(ConfigError, match=_err(path, f"is not a complete codesign training checkpoint: no {missing} "
                                                     f"entry$")):
        load_trained(path, CPU)


def test_stored_configuration_this_version_refuses(trained, tmp_path):
    state = copy.deepcopy(trained)
    state["config"]["model"]["depth"] = 3  # e.g. a key of an older version
    path = _save(tmp_path, state)
    with pytest.raises(ConfigError, match=_err(path, "its stored configuration is not valid in this version of "
                                                     "codesign: model.depth = 3: unknown key")):
        load_trained(path, CPU)


@pytest.mark.parametrize("key,value,message", [
    ("variant", "sgan_f", r"\(model.kind=sgan, variant=sgan_f, size=tiny\): \d+ tensor\(s\) missing \(e.g. 'g1\."),
    ("size", "cpu", r"\(model.kind=sgan, variant=sgan_b, size=cpu\): \d+ tensor\(s\) missing .*; \d+ of another shape "
                    r"\(e.g. '.*': \[4, .*\] in the file, \[16, .*\] here\)"),
], ids=["variant", "size"])
def test_weights_of_another_model_variant_or_size(trained, tmp_path, key, value, message):
    state = copy.deepcopy(trained)
    state["config"]["model"][key] = value  # the weights stay those of tiny SGAN-B
    path = _save(tmp_path, state)
    with pytest.raises(ConfigError, match=_err(path, "its weights do not fit the model its configuration describes "
                                                     + message + ".*" + re.escape(FOREIGN) + "$")):
        load_trained(path, CPU)


def test_a_plug_in_restorer_s_checkpoint_loads_and_its_misfit_is_named(tmp_path):
    """evaluate / restore read any restorer's checkpoint through the interface (not SGAN's spec fields)."""
    cfg = tiny_cfg("model=wiener_unet", "model.size=tiny")
    torch.manual_seed(0)
    model = build_model(cfg)
    state = {"model": model.state_dict(), "step": 4, "config": OmegaConf.to_container(cfg, resolve=True)}
    loaded, generators, _, _ = load_trained(_save(tmp_path, state), CPU)
    assert loaded.kind == "wiener_unet" and len(generators) == len(model.generators())
    assert all(torch.equal(a, b) for a, b in zip(loaded.state_dict().values(), model.state_dict().values()))
    state["config"]["model"]["size"] = "cpu"
    path = _save(tmp_path, state, "cpu.pt")
    with pytest.raises(ConfigError, match=_err(path, "its weights do not fit the model its configuration describes "
                                                     r"\(model.kind=wiener_unet, variant=wiener_unet, size=cpu\): ")):
        load_trained(path, CPU)


def test_ema_weights_are_checked_like_the_model(trained, tmp_path):
    model = build_model(tiny_cfg())
    ema = [g.state_dict() for g in model.generators()]
    _, generators, _, _ = load_trained(_save(tmp_path, {**trained, "ema": ema}), CPU)
    assert len(generators) == len(ema)
    path = _save(tmp_path, {**trained, "ema": ema[:1]})
    with pytest.raises(ConfigError, match=_err(path, r"its weights do not fit .*: its EMA holds 1 generator "
                                                     rf"state\(s\), the model has {len(ema)} generators")):
        load_trained(path, CPU)


def test_learned_mask_of_another_mask_type(tmp_path):
    spec = OpticsSpec.with_samples_across(24, focal_n=32)
    mask = HalfRingMask(OpticalSystem(spec, dtype=torch.float32).grid, spec.aperture_diameter_m)  # five rings
    state = {"mask": {"r": torch.ones(3), "theta": torch.ones(3)}}  # a three-ring mask's
    with pytest.raises(ConfigError, match=_err(tmp_path / "ck.pt", r"its learned mask does not fit the HalfRingMask "
                                               r"of its configuration: 2 of another shape \(e.g. 'r': \[3\] in the "
                                               r"file, \[5\] here\)" + re.escape(FOREIGN) + "$")):
        apply_checkpoint_mask(mask, state, tmp_path / "ck.pt")


def test_resume_under_another_configuration_names_the_file_the_keys_and_both_values(trained, tmp_path):
    """Issue 59: a resume refused names each differing setting with the checkpoint's value and this run's."""
    saved = copy.deepcopy(trained["config"])
    saved["model"]["variant"], saved["mask"]["convention"] = "sgan_f", "atan"
    path = tmp_path / "run" / "checkpoint.pt"
    with pytest.raises(ConfigError, match="^trainer.resume = " + re.escape(repr(str(path))) + re.escape(
            ": was trained with different model, mask (model.variant = 'sgan_f' there, 'sgan_b' here; "
            "mask.convention = 'atan' there, 'atan2' here): resume with the same settings, or start a new run "
            "directory") + "$"):
        check_resume_config(saved, tiny_cfg(), "trainer.resume", path=path)


def test_resume_under_another_seed_is_refused(trained, tmp_path):
    """Issue 59: the final evaluation draws from the seed and the run records it as its own; the training itself
    would continue the same (the checkpoint restores the random state)."""
    saved = copy.deepcopy(trained["config"])
    cfg = tiny_cfg()
    saved["seed"] = int(cfg.seed) + 1
    with pytest.raises(ConfigError, match=re.escape(f"was trained with different seed (seed = {cfg.seed + 1} there, "
                                                    f"{cfg.seed} here): resume with the same settings")):
        check_resume_config(saved, cfg, "trainer.resume", path=tmp_path / "checkpoint.pt")


def test_resume_checks_the_file_before_touching_the_trainer(trained, tmp_path):
    cfg = tiny_cfg()
    loaded = []
    trainer = SimpleNamespace(model=build_model(cfg), step=0, load_state_dict=loaded.append)
    run_dir = tmp_path / "run"
    state = {**copy.deepcopy(trained), "opt_g": {}, "opt_d": {}, "sched_g": {}, "sched_d": {}, "rng": {}}
    del state["model"]["g1.head.0.0.weight"]  # same configuration, weights from another code version
    path = _save(run_dir, state, "checkpoint.pt")  # a killed run's own checkpoint, resumed automatically
    with pytest.raises(ConfigError, match="^trainer.resume = " + re.escape(repr(str(path))) + ": cannot be resumed: "
                       r"its weights do not fit this run's model: 1 tensor\(s\) missing \(e.g. 'g1.head.0.0.weight'\)"):
        resume_if_possible(trainer, cfg, run_dir)
    del state["opt_g"]
    _save(run_dir, state, "checkpoint.pt")
    with pytest.raises(ConfigError, match="^trainer.resume = " + re.escape(repr(str(path))) + ": is not a complete "
                       "codesign training checkpoint: no opt_g entry$"):
        resume_if_possible(trainer, cfg, run_dir)
    assert loaded == []  # nothing was loaded into the trainer


def test_evaluate_with_a_truncated_checkpoint_exits_2_before_any_work(trained, tmp_path, monkeypatch, capsys):
    path = _save(tmp_path, trained)
    path.write_bytes(path.read_bytes()[:1000])
    line = config_error(monkeypatch, capsys, tmp_path / "run", "+experiment=evaluate", "debug=smoke",
                        f"checkpoint={path}")
    assert line == (f"codesign: configuration error: checkpoint = '{path}': is truncated or corrupt "
                    f"(PytorchStreamReader failed reading zip archive: failed finding central directory); copy it "
                    f"again, or use an earlier checkpoint")


@pytest.mark.slow  # 4 s: the same refusal through the command line; twin: the in-process test above
def test_cli_evaluate_with_a_truncated_checkpoint(trained, tmp_path):
    path = _save(tmp_path, trained)
    path.write_bytes(path.read_bytes()[:1000])
    run_dir = tmp_path / "run"
    proc = run_codesign("+experiment=evaluate", "debug=smoke", "threads=1", f"checkpoint={path}",
                        f"hydra.run.dir={run_dir}")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1] == (
        f"codesign: configuration error: checkpoint = '{path}': is truncated or corrupt (PytorchStreamReader failed "
        f"reading zip archive: failed finding central directory); copy it again, or use an earlier checkpoint")
    assert "Traceback" not in proc.stderr and not run_dir.exists()


@pytest.mark.parametrize("step", [-5, 4.7, 1e30, True, "abc"], ids=["negative", "fraction", "huge", "bool", "text"])
def test_a_step_that_is_no_count_of_steps_is_refused_at_load(trained, tmp_path, step):
    # -5, 4.7 and True were reported as the steps trained (evaluate's metrics.json, a warm start's record), 1e30 as a
    # 31-digit count, "abc" a ValueError traceback after the evaluation had run
    path = _save(tmp_path, {**trained, "step": step})
    with pytest.raises(ConfigError, match=_err(path, "its entry step = " + re.escape(repr(step)) + r": must be an "
                                                     r"integer >= 0 and <= 1e\+07 \(the training steps it holds\)$")):
        load_trained(path, CPU)


def test_a_resumed_checkpoint_s_step_is_checked_before_the_trainer_is_touched(trained, tmp_path):
    cfg = tiny_cfg()
    loaded = []
    trainer = SimpleNamespace(model=build_model(cfg), step=0, load_state_dict=loaded.append,
                              spec=SimpleNamespace(steps=10))
    run_dir = tmp_path / "run"
    state = {**trained, "step": -5, "opt_g": {}, "opt_d": {}, "sched_g": {}, "sched_d": {}, "rng": {}}
    path = _save(run_dir, state, "checkpoint.pt")
    with pytest.raises(ConfigError, match="^trainer.resume = " + re.escape(repr(str(path))) + ": its entry step = -5: "
                       "must be an integer >= 0"):
        resume_if_possible(trainer, cfg, run_dir)
    assert loaded == []


@pytest.mark.parametrize("dtype", [torch.int64, torch.int32, torch.uint8, torch.bool])
def test_integer_weights_are_refused_naming_the_tensor_and_its_dtype(trained, tmp_path, dtype):
    # int64 weights were copied into the float model without a word (every weight rounded: 0.03 -> 0)
    state = copy.deepcopy(trained)
    name = next(k for k, v in state["model"].items() if v.is_floating_point())
    state["model"][name] = state["model"][name].to(dtype)
    path = _save(tmp_path, state)
    with pytest.raises(ConfigError, match=_err(path, r"its weights do not fit .*: tensor " + re.escape(repr(name)) +
                                                     f" holds {str(dtype).replace('torch.', '')} values where the "
                                                     r"model has float32 \(allowed: floating point\)")):
        load_trained(path, CPU)


def test_integer_buffers_of_the_model_itself_stay_allowed(tmp_path):
    # a BatchNorm's num_batches_tracked is int64 in the model too: only a floating tensor stored as integers is wrong
    module = torch.nn.BatchNorm1d(3)
    from codesign.train.checkpoint import load_module_state
    load_module_state(module, module.state_dict(), "checkpoint", tmp_path / "ck.pt", "its weights")
