"""SIGINT and SIGTERM outside training: every experiment stops with one line on stderr and exit 128 + the signal,
keeps what it finished (a search's best design so far as a record marked partial, a Monte Carlo's finished
sources) and leaves nothing half-written; the search reports its stop as an interrupt, never as nlopt's own end.

The in-process tests send the signal to this process at a chosen point of the run; a handler installed for each
test turns a signal the code under test does not handle into a test failure (instead of killing pytest)."""
from __future__ import annotations

import csv
import json
import logging
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from omegaconf import OmegaConf

import codesign.experiments as experiments
from codesign.config.runtime import command_line_keys
from codesign.design.problem import DesignProblem
from codesign.errors import ConfigError
from codesign.fab.tolerance import PlateEvaluator
from codesign.optics import OpticalSystem, OpticsSpec, build_mask
from codesign.train.checkpoint import save_checkpoint
from codesign.train.model_setup import build_model
from tests.conftest import REPO_ROOT
from tests.inputs._run import compose_cfg
from tests.train._util import tiny_cfg

NAMES = {signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM"}


class SignalNotHandled(Exception):
    """The signal reached the test's own handler: the code under test did not handle it."""


@pytest.fixture(autouse=True)
def _unhandled_signals_fail_the_test():
    old = {s: signal.getsignal(s) for s in NAMES}

    def fail(signum, frame):
        raise SignalNotHandled(NAMES[signum])

    for s in NAMES:
        signal.signal(s, fail)
    yield
    for s, handler in old.items():
        signal.signal(s, handler)


def signal_self(sig: int) -> None:
    """Deliver ``sig`` to this process's main thread, as Ctrl-C or a scheduler's SIGTERM would, and give its handler
    the chance to run here."""
    signal.pthread_kill(threading.main_thread().ident, sig)
    time.sleep(0.02)


def run(monkeypatch, capsys, run_dir: Path, *overrides: str) -> tuple[int, list[str], str]:
    """(exit status, the stderr lines starting "codesign: ", all of stderr) of run_experiment on ``overrides``."""
    monkeypatch.setattr(experiments, "explicit_keys", lambda: command_line_keys(list(overrides)))
    cfg = compose_cfg(*overrides)
    with pytest.raises(SystemExit) as info:
        experiments.run_experiment(cfg, run_dir=run_dir)
    err = capsys.readouterr().err
    return info.value.code, [line for line in err.splitlines() if line.startswith("codesign: ")], err


def outputs(run_dir: Path) -> set[str]:
    return {p.name for p in run_dir.iterdir()} if run_dir.is_dir() else set()


def no_temp_files(run_dir: Path) -> bool:
    return not [p for p in run_dir.rglob("*") if p.name.endswith(".tmp")]


# ---- mask_search: the best design so far as a partial record; the stop reported as an interrupt -----------------
@pytest.mark.parametrize("sig,algorithm", [(signal.SIGINT, "LN_COBYLA"), (signal.SIGTERM, "AL_LBFGS")],
                         ids=["SIGINT-LN_COBYLA", "SIGTERM-AL_LBFGS"])
def test_a_signal_stops_the_mask_search_and_keeps_its_best_design_as_a_partial_record(
        monkeypatch, capsys, caplog, tmp_path, sig, algorithm):
    """Ctrl-C used to be swallowed by nlopt ("MAXEVAL_REACHED (runtime_error)") and the search went on to exit 0;
    SIGTERM ended it with 143, nothing on stderr and nothing saved."""
    real, calls = DesignProblem.evaluate, []

    def evaluate(self, *args, **kwargs):
        calls.append(1)
        out = real(self, *args, **kwargs)
        if len(calls) == 6:
            signal_self(sig)
        return out

    monkeypatch.setattr(DesignProblem, "evaluate", evaluate)
    caplog.set_level(logging.INFO)
    code, lines, err = run(monkeypatch, capsys, tmp_path, "+experiment=mask_search", "debug=smoke",
                           f"search.algorithm={algorithm}", "search.max_evals=400", "logging.tensorboard=false")
    name = NAMES[sig]
    assert code == 128 + sig and len(lines) == 1 and "Traceback" not in err, err[-3000:]
    partial = tmp_path / "best_mask.partial.json"
    assert lines[0].startswith(f"codesign: {name}: the search stopped in start 0 of the search after 6 of "), lines
    assert f"its best design so far: {partial} (marked partial" in lines[0]
    assert len(calls) <= 7  # stopped at the next evaluation, not at the end of the budget
    record = json.loads(partial.read_text())
    assert record["partial"] is True and record["stop_reason"].startswith(f"interrupted by {name}: the search stopped")
    assert record["kind"] == "halfring" and record["feasible"] is True
    assert not {"best_mask.json", "metrics.json", "evaluations.csv"} & outputs(tmp_path) and no_temp_files(tmp_path)
    text = caplog.text
    assert f"{algorithm} stopped: INTERRUPTED by {name}" in text
    assert "MAXEVAL_REACHED" not in text and "runtime_error" not in text and "FORCED_STOP" not in text


def _published_record(tmp_path: Path, **extra) -> tuple:
    spec = OpticsSpec(pupil_pitch_m=6.0e-5, focal_n=128)
    system = OpticalSystem(spec)
    mask = build_mask({"kind": "halfring", "preset": "published"}, system.grid, spec.aperture_diameter_m)
    path = tmp_path / "best_mask.partial.json"
    path.write_text(json.dumps({**mask.record(), **extra}))
    return path, system, spec


def test_a_partial_record_is_read_with_a_warning_never_as_a_finished_design(tmp_path, caplog):
    why = "interrupted by SIGINT: the search stopped in start 0 of the search after 6 of 800 evaluations"
    path, system, spec = _published_record(tmp_path, partial=True, stop_reason=why)
    caplog.set_level(logging.WARNING)
    mask = build_mask({"kind": "halfring", "init": str(path)}, system.grid, spec.aperture_diameter_m)
    assert mask.vector_size == 10
    assert f"mask.init={path} is a PARTIAL record" in caplog.text and why in caplog.text


@pytest.mark.parametrize("extra,message", [
    ({"partial": True}, r'partial record .*"partial": true and its "stop_reason"'),
    ({"partial": False, "stop_reason": "interrupted"}, r'partial record .*"partial": true and its "stop_reason"'),
    ({"partial": "yes", "stop_reason": "interrupted"}, r"partial = 'yes': must be true, false or null"),
], ids=["true-without-reason", "reason-without-true", "not-a-flag"])
def test_a_malformed_partial_flag_is_refused(tmp_path, extra, message):
    path, system, spec = _published_record(tmp_path, **extra)
    with pytest.raises(ConfigError, match=message):
        build_mask({"kind": "halfring", "init": str(path)}, system.grid, spec.aperture_diameter_m)


# ---- tolerance: the finished sources' samples kept apart from samples.csv ----------------------------------------
def test_sigterm_in_tolerance_keeps_the_samples_of_the_sources_that_finished(monkeypatch, capsys, tmp_path):
    real, monte_carlo = PlateEvaluator.__call__, []

    def evaluate(self, e, progress=None):
        if progress is not None:  # a Monte Carlo batch (not the nominal or a +-1 sigma point)
            monte_carlo.append(len(e))
            if len(monte_carlo) == 2:  # the first source finished
                signal_self(signal.SIGTERM)
        return real(self, e, progress)

    monkeypatch.setattr(PlateEvaluator, "__call__", evaluate)
    code, lines, err = run(monkeypatch, capsys, tmp_path, "+experiment=tolerance", "debug=smoke")
    assert code == 143 and len(lines) == 1 and "Traceback" not in err, err[-3000:]
    partial = tmp_path / "samples.partial.csv"
    assert lines[0].startswith("codesign: SIGTERM: the Monte Carlo stopped after 4 of ") and str(partial) in lines[0]
    rows = list(csv.DictReader(partial.open()))
    assert len(rows) == monte_carlo[0] == 4 and len({r["source"] for r in rows}) == 1
    assert not {"samples.csv", "metrics.json", "tolerance.png"} & outputs(tmp_path) and no_temp_files(tmp_path)


# ---- export and evaluate: one line, the finished files kept, nothing half-written ------------------------------
def test_sigint_in_export_keeps_the_files_it_finished(monkeypatch, capsys, tmp_path):
    from codesign.experiments import export

    def write_tiff(*args, **kwargs):
        signal_self(signal.SIGINT)
        raise AssertionError("the interrupt did not stop the run")

    monkeypatch.setattr(export, "write_height_tiff", write_tiff)
    code, lines, err = run(monkeypatch, capsys, tmp_path, "+experiment=export", "debug=smoke")
    assert code == 130 and len(lines) == 1 and "Traceback" not in err, err[-3000:]
    assert lines[0] == (f"codesign: SIGINT: +experiment=export stopped before it finished; kept in {tmp_path}: "
                        f"height.png, height_m.npy (the run is not finished)")
    assert {"height.png", "height_m.npy"} <= outputs(tmp_path) and no_temp_files(tmp_path)
    assert not {"height.tif", "export.json", "metrics.json"} & outputs(tmp_path)


def test_sigterm_in_evaluate_exits_143_with_one_line(monkeypatch, capsys, tmp_path):
    from codesign.experiments import evaluate

    cfg = tiny_cfg()
    torch.manual_seed(0)
    state = {"model": build_model(cfg).state_dict(), "step": 4, "config": OmegaConf.to_container(cfg, resolve=True)}
    checkpoint = save_checkpoint(tmp_path / "ck.pt", state)

    def run_evaluation(*args, **kwargs):
        signal_self(signal.SIGTERM)
        raise AssertionError("the interrupt did not stop the run")

    monkeypatch.setattr(evaluate, "run_evaluation", run_evaluation)
    run_dir = tmp_path / "run"
    code, lines, err = run(monkeypatch, capsys, run_dir, "+experiment=evaluate", "debug=smoke",
                           f"checkpoint={checkpoint}")
    assert code == 143 and len(lines) == 1 and "Traceback" not in err, err[-3000:]
    assert lines[0] == ("codesign: SIGTERM: +experiment=evaluate stopped before it finished; no output file written "
                        "(the run is not finished)")
    assert "metrics.json" not in outputs(run_dir)


@pytest.mark.parametrize("task,attribute,sig", [("psf", "time_forward_backward", signal.SIGTERM),
                                                ("simulate", "build_camera", signal.SIGINT)])
def test_the_other_experiments_stop_with_one_line_and_the_signal_s_status(monkeypatch, capsys, tmp_path, task,
                                                                          attribute, sig):
    def work(*args, **kwargs):
        signal_self(sig)
        raise AssertionError("the interrupt did not stop the run")

    monkeypatch.setattr(experiments.experiment_module(task), attribute, work)
    code, lines, err = run(monkeypatch, capsys, tmp_path, f"+experiment={task}", "debug=smoke")
    assert code == 128 + sig and len(lines) == 1 and "Traceback" not in err, err[-3000:]
    assert lines[0].startswith(f"codesign: {NAMES[sig]}: +experiment={task} stopped before it finished; ")
    assert lines[0].endswith(" (the run is not finished)") and no_temp_files(tmp_path)


# ---- the command line: Ctrl-C in a real mask_search process ------------------------------------------------------
def test_ctrl_c_in_a_mask_search_process_exits_130_with_a_partial_record(tmp_path):
    run_dir = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "codesign", "+experiment=mask_search", "debug=smoke",
                             "search.max_evals=4000", "search.log_every=5", "logging.tensorboard=false",
                             f"hydra.run.dir={run_dir}"], cwd=REPO_ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # as in a terminal
    log, t_end = run_dir / "__main__.log", time.time() + 120
    while time.time() < t_end and proc.poll() is None:
        if log.is_file() and "eval 10:" in log.read_text():
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()  # a search that went on (Ctrl-C swallowed) is not left running
    assert proc.returncode == 130, err[-3000:]
    assert len(err.strip().splitlines()) == 1 and err.startswith("codesign: SIGINT: the search stopped in start 0")
    assert json.loads((run_dir / "best_mask.partial.json").read_text())["partial"] is True
    assert not (run_dir / "metrics.json").exists() and no_temp_files(run_dir)


# ---- the main job between its stages ----------------------------------------------------------------------------
FIVE = ("design", "restorer", "published_restorer", "designed", "codesigned")


def _main_job_folder(tmp_path) -> tuple[Path, dict]:
    """A main job's run folder whose first five stages finished (their metrics.json), the last not started."""
    from codesign.experiments.main_job import STAGES

    run_dir = tmp_path / "run"
    stages = {s: run_dir / s for s in STAGES}
    for s in FIVE:
        stages[s].mkdir(parents=True)
        (stages[s] / "metrics.json").write_text("{}")
    (run_dir / "stage_seconds.json").write_text("{}")
    return run_dir, stages


def test_sigint_between_the_main_job_s_stages_lists_the_finished_stages_and_the_resume_command(tmp_path, monkeypatch):
    # the line said only "kept in RUN: stage_seconds.json" (the stages are folders) and gave no resume command, while
    # the five finished stages were kept and are reused by the same command
    from codesign.experiments import main_job
    from codesign.signals import Interrupted
    from codesign.train import distributed

    run_dir, stages = _main_job_folder(tmp_path)
    monkeypatch.setattr(sys, "argv", ["codesign", "+experiment=joint", "debug=smoke", f"hydra.run.dir={run_dir}"])
    monkeypatch.setattr(main_job, "_build", lambda cfg, rd, device: SimpleNamespace(stages=stages))
    monkeypatch.setattr(main_job, "_design_stage", lambda job: ({}, None))

    def last_stage_starts(job, designed_cfg, train):
        raise Interrupted(signal.SIGINT)  # as the last stage starts: outside any training loop

    monkeypatch.setattr(main_job, "_train_stages", last_stage_starts)
    with pytest.raises(Interrupted) as info:
        main_job.run_protocol(None, run_dir, torch.device("cpu"), None)
    line = experiments.interrupt_line(info.value, run_dir, distributed.current(), "joint")
    assert line == (f"SIGINT: +experiment=joint stopped before it finished; finished stages kept in {run_dir}: "
                    f"design/, restorer/, published_restorer/, designed/, codesigned/ (each reused when the run "
                    f"resumes), and stage_seconds.json (the run is not finished); resume with: python -m codesign "
                    f"+experiment=joint debug=smoke hydra.run.dir={run_dir}")


def test_an_interrupt_before_any_stage_finished_still_gives_the_resume_command(tmp_path, monkeypatch):
    from codesign.experiments.main_job import STAGES, note_finished_stages
    from codesign.signals import Interrupted
    from codesign.train import distributed

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    monkeypatch.setattr(sys, "argv", ["codesign", "+experiment=joint"])
    stop = Interrupted(signal.SIGTERM)
    note_finished_stages(stop, {s: run_dir / s for s in STAGES})
    line = experiments.interrupt_line(stop, run_dir, distributed.current(), "joint")
    assert line == (f"SIGTERM: +experiment=joint stopped before it finished; no stage finished, no output file "
                    f"written (the run is not finished); resume with: python -m codesign +experiment=joint "
                    f"hydra.run.dir={run_dir}")
