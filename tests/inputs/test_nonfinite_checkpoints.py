"""Non-finite checkpoints and outputs (issue 38): a checkpoint with a NaN or inf anywhere (weights, buffers, EMA,
optimizer state, learned mask) is refused by every experiment that loads one (evaluate, restore, init.checkpoint,
resume) before any work, naming the file and the first bad tensor; a restorer whose output is not finite stops the
run instead of writing black images or "nan dB"; a value of a checkpoint's stored configuration is named as stored
in that file, not as if typed on the command line."""
from __future__ import annotations

import copy
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

import codesign.experiments as experiments
from codesign.config.runtime import command_line_keys
from codesign.errors import ConfigError
from codesign.io.captures import save_png16
from codesign.train.checkpoint import load_checkpoint, save_checkpoint
from codesign.train.model_setup import build_model
from codesign.train.resume import load_trained
from codesign.experiments.resume import load_initial_weights, resume_if_possible
from tests.inputs._run import compose_cfg, config_error
from tests.train._util import tiny_cfg

CPU = torch.device("cpu")
FIRST = "g1.head.0.0.weight"  # the first tensor of a tiny SGAN-B's state dict (588 values)
USE_EARLIER = ("(the first non-finite tensor in the file; results computed from it would be NaN): use an earlier "
               "checkpoint of the run")


def smoke_trained(experiment: str) -> dict:
    """The same as a +experiment=``experiment`` debug=smoke run writes it: a warm start of that run accepts its
    settings (the code before issue 38 went on to train from its NaN weights)."""
    cfg = compose_cfg(f"+experiment={experiment}", "debug=smoke")
    experiments.apply_debug(cfg)
    torch.manual_seed(0)
    model = build_model(cfg)
    return {"model": model.state_dict(), "step": 4, "config": OmegaConf.to_container(cfg, resolve=True)}


def _save(tmp_path, state, name="ck.pt"):
    return save_checkpoint(tmp_path / name, state)


def _refusal(key, path, where, what):
    return f"{key} = '{path}': is not usable: tensor {where} holds {what} {USE_EARLIER}"


def _poisoned(trained, entry):
    """``trained`` with one bad value where ``entry`` says; (state, where, what) of the tensor named."""
    state = copy.deepcopy(trained)
    generators = [{k.split(".", 1)[1]: v.clone() for k, v in state["model"].items() if k.startswith(g + ".")}
                  for g in ("g1", "g2")]
    if entry == "all-nan":  # a diverged run's weights
        state["model"] = {k: torch.full_like(v, float("nan")) if v.is_floating_point() else v
                          for k, v in state["model"].items()}
        first, n = next((k, v.numel()) for k, v in state["model"].items() if v.is_floating_point())  # any network
        return state, f"model['{first}']", f"{n} NaN of {n} values"
    if entry == "one-inf":
        state["model"][FIRST].view(-1)[7] = float("inf")
        return state, f"model['{FIRST}']", "1 +inf of 588 values"
    if entry == "ema":
        state["ema"] = generators
        first = next(iter(generators[1]))
        generators[1][first].view(-1)[:2] = float("-inf")
        return state, f"ema[1][{first!r}]", f"2 -inf of {generators[1][first].numel()} values"
    if entry == "adam":
        state["opt_g"] = {"state": {0: {"step": torch.tensor(3.0), "exp_avg": torch.zeros(3),
                                        "exp_avg_sq": torch.tensor([0.0, float("nan"), float("inf")])}}}
        return state, "opt_g['state'][0]['exp_avg_sq']", "1 NaN and 1 +inf of 3 values"
    state["mask"] = {"r": torch.ones(5), "theta": torch.full((5,), float("nan"))}  # a learned mask
    return state, "mask['theta']", "5 NaN of 5 values"


@pytest.mark.parametrize("entry", ["all-nan", "one-inf", "ema", "adam", "mask"])
def test_a_nonfinite_tensor_anywhere_is_refused_naming_the_file_and_tensor(trained, tmp_path, entry):
    state, where, what = _poisoned(trained, entry)
    path = _save(tmp_path, state)
    with pytest.raises(ConfigError) as info:
        load_checkpoint(path)
    assert str(info.value) == _refusal("checkpoint", path, where, what)
    with pytest.raises(ConfigError) as info:  # what evaluate and restore load through
        load_trained(path, CPU)
    assert str(info.value) == _refusal("checkpoint", path, where, what)


def test_resume_and_warm_start_refuse_a_nonfinite_checkpoint(trained, tmp_path):
    state, where, what = _poisoned(trained, "all-nan")
    state.update({"opt_g": {}, "opt_d": {}, "sched_g": {}, "sched_d": {}, "rng": {}})
    cfg = tiny_cfg()
    model = build_model(cfg)
    before = copy.deepcopy(model.state_dict())
    path = _save(tmp_path, state)
    with pytest.raises(ConfigError) as info:
        load_initial_weights(model, path, cfg)
    assert str(info.value) == _refusal("init.checkpoint", path, where, what)
    run_dir = tmp_path / "run"
    auto = _save(run_dir, state, "checkpoint.pt")  # a killed run's own checkpoint, resumed automatically
    loaded = []
    trainer = SimpleNamespace(model=model, step=0, load_state_dict=loaded.append)
    with pytest.raises(ConfigError) as info:
        resume_if_possible(trainer, cfg, run_dir)
    assert str(info.value) == _refusal("trainer.resume", auto, where, what)
    assert loaded == [] and all(torch.equal(v, model.state_dict()[k]) for k, v in before.items())


def _captures(tmp_path, size=48):
    folder = tmp_path / "captures"
    folder.mkdir()
    save_png16(folder / "a.png", np.random.default_rng(0).uniform(100, 3000, (size, size)))
    return folder


@pytest.mark.parametrize("experiment", ["evaluate", "restore", "baseline", "joint"])
def test_every_experiment_refuses_a_nan_checkpoint_before_any_work(trained, tmp_path, monkeypatch, capsys,
                                                                   experiment):
    """Before: evaluate "sgan nan dB" (exit 0), restore all-zero images (exit 0), a warm start trained to the end
    and then advised lowering the learning rates."""
    warm = experiment in ("baseline", "joint")
    state, where, what = _poisoned(smoke_trained(experiment) if warm else trained, "all-nan")
    path = _save(tmp_path, state)
    key = "init.checkpoint" if warm else "checkpoint"
    extra = [f"input={_captures(tmp_path)}"] if experiment == "restore" else []
    line = config_error(monkeypatch, capsys, tmp_path / "run", f"+experiment={experiment}", "debug=smoke",
                        f"{key}={path}", *extra)
    assert line == "codesign: configuration error: " + _refusal(key, path, where, what)


@pytest.mark.parametrize("change,message", [
    ({"data": {"image_size": 4096}}, "data.padded_size = 64: must be an integer >= data.image_size (4096)"),
    ({"mask": {"preset": None, "r": [float("nan"), 30.0], "theta": [1.0, 2.0]}},
     "mask.r[0] = nan: must be a finite number"),
], ids=["image_size-4096", "mask-r-nan"])
def test_evaluate_names_a_stored_value_as_the_checkpoint_s(trained, tmp_path, monkeypatch, capsys, change, message):
    """Before: "codesign: configuration error: data.padded_size = 64: ..." as if typed on the command line."""
    state = copy.deepcopy(trained)
    for block, values in change.items():
        state["config"][block].update(values)
    path = _save(tmp_path, state)
    line = config_error(monkeypatch, capsys, tmp_path / "run", "+experiment=evaluate", "debug=smoke",
                        f"checkpoint={path}")
    assert line == (f"codesign: configuration error: checkpoint = '{path}': its stored configuration is not valid "
                    f"in this version of codesign: {message}")


def _overflowing(trained):
    """Finite weights whose output is not: G2's convolutions scaled by 1e30 overflow to inf, then NaN."""
    state = copy.deepcopy(trained)
    for k, v in state["model"].items():
        if k.startswith("g2.") and k.endswith("weight"):
            state["model"][k] = v * 1e30
    return state


def _run(monkeypatch, capsys, run_dir, *overrides: str) -> str:
    """The last stderr line of a whole in-process run that must exit with 2 (the work not replaced)."""
    monkeypatch.setattr(experiments, "explicit_keys", lambda: command_line_keys(list(overrides)))
    with pytest.raises(SystemExit) as info:
        experiments.run_experiment(compose_cfg(*overrides), run_dir=run_dir)
    assert info.value.code == 2
    return capsys.readouterr().err.strip().splitlines()[-1]


def test_restore_stops_on_a_nonfinite_restoration_and_writes_nothing(trained, tmp_path, monkeypatch, capsys):
    """Before: restored_a.png written all zeros (NaN cast to 0), exit 0."""
    path = _save(tmp_path, _overflowing(trained))
    captures, run_dir = _captures(tmp_path), tmp_path / "run"
    line = _run(monkeypatch, capsys, run_dir, "+experiment=restore", "threads=1", f"input={captures}",
                f"checkpoint={path}")
    assert line == (f"codesign: configuration error: checkpoint = '{path}': its network restores input "
                    f"{captures / 'a.png'} to 2304 NaN of 2304 values (not finite): its weights are finite but the "
                    f"network does not compute finite images; nothing written")
    assert not list(run_dir.glob("restored_*")) and not (run_dir / "metrics.json").exists()


def test_evaluate_stops_on_a_nonfinite_restoration(trained, tmp_path, monkeypatch, capsys):
    """Before: exit 0, tables and figures of "sgan nan dB"."""
    path = _save(tmp_path, _overflowing(trained))
    run_dir = tmp_path / "run"
    line = _run(monkeypatch, capsys, run_dir, "+experiment=evaluate", "debug=smoke", "threads=1",
                f"checkpoint={path}")
    assert line == (f"codesign: configuration error: checkpoint = '{path}': its network's output 'restored' on the "
                    f"evaluation's simulated captures holds 8192 NaN of 8192 values: its weights are finite but the "
                    f"network does not compute finite images (evaluation stopped, no metrics.json)")
    assert not (run_dir / "metrics.json").exists() and not list(run_dir.glob("panel_*"))
