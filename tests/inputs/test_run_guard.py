"""One run-folder guard wherever a run starts (issue 59): every job of a sweep and the sweep's own folder, the
Python API, torchrun's ranks and a resume are refused where the single command is (the user's files, another
experiment's results, a finished run, a folder in use); no run writes through a symbolic link; a config-error
clean-up removes only what the run made; a finished run is never rewritten in place."""
from __future__ import annotations

import copy
import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from hydra.types import RunMode
from omegaconf import OmegaConf

import codesign
from codesign.config import CONF_DIR
from codesign.errors import ConfigError
from codesign.experiments import rundir, runlock, runstart
from tests.inputs._run import fresh_run_folder_state  # noqa: F401 (autouse: the guard's records, fresh per test)
from codesign.train import distributed
from codesign.train.checkpoint import save_checkpoint
from codesign.train.model_setup import build_model
from codesign.experiments.resume import resume_if_possible
from tests.cli import run_codesign
from tests.inputs._run import WorkStarted, compose_cfg, config_error, stop_before_work
from tests.train._util import tiny_cfg

STATE = ".codesign-run.json"


def _choose(key: str, what: str = "run") -> str:
    return f"choose another folder with {key}=PATH (or leave {key} unset: every {what} gets a new one)"


def _link_refusal(key: str, folder: Path, link: str, target: Path) -> str:
    return (f"{key} = '{folder}': holds a symbolic link: {link} -> {target}; a run never writes through a link (it "
            f"would change files outside its folder): replace the link by a real file or folder, or choose another "
            f"folder with {key}=PATH")


def _tree(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _run_folder(run_dir: Path, task: str, state: str, *outputs: str) -> Path:
    """A folder as a run of ``task`` leaves it: its recorded config, its outputs, its completion marker."""
    (run_dir / ".hydra").mkdir(parents=True)
    (run_dir / ".hydra" / "config.yaml").write_text(f"task: {task}\nseed: 0\n")
    for name in outputs:
        (run_dir / name).write_bytes(b"earlier run's " + name.encode())
    (run_dir / STATE).write_text(json.dumps({"task": task, "state": state, "pid": 1}))
    return run_dir


def _sweep_record(top: Path, task: str) -> None:
    """multirun.yaml as Hydra writes it at a sweep's top (its hydra.sweep and the task)."""
    top.mkdir(parents=True, exist_ok=True)
    (top / "multirun.yaml").write_text(f"hydra:\n  sweep:\n    dir: {top}\n    subdir: ${{hydra.job.num}}\n"
                                       f"  mode: MULTIRUN\ntask: {task}\n")


def _sweep(top: Path, *args: str):
    return run_codesign("-m", "+experiment=psf", "debug=smoke", *args, f"hydra.sweep.dir={top}", "seed=0")


def _last(proc) -> str:
    return proc.stderr.strip().splitlines()[-1]




# ---- sweeps: the top folder and every job folder -------------------------------------------------------------
def test_a_second_sweep_into_the_same_folder_keeps_the_finished_job(tmp_path):
    """The issue's case: a second sweep into one folder overwrote the finished job 0/ (exit 0)."""
    top = tmp_path / "sweep"
    _sweep_record(top, "psf")
    _run_folder(top / "0", "psf", "finished", "metrics.json", "psf.npy")
    before = _tree(top)
    proc = _sweep(top)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert _last(proc) == (
        f"codesign: configuration error: hydra.sweep.dir = '{top / '0'}': holds a finished +experiment=psf run "
        f"(metrics.json, psf.npy); psf does not resume, and a rerun would overwrite it: "
        f"{_choose('hydra.sweep.dir')}")
    assert _tree(top) == before  # multirun.yaml and the job's .hydra/ too


@pytest.mark.parametrize("earlier,refusal", [
    ("users_file", "holds files that no codesign run wrote (psf.npy); +experiment=psf writes only into an empty "
                   "folder or its own earlier run's, never over files of yours"),
    ("simulate_job", "holds the results of +experiment=simulate (metrics.json, sensor.png); +experiment=psf never "
                     "writes into another experiment's folder"),
], ids=["users_file", "simulate_job"])
def test_a_job_folder_that_is_not_free_is_refused_untouched(tmp_path, earlier, refusal):
    """The issue's cases: a job folder holding the user's psf.npy overwritten; psf written into a finished
    simulate job's folder."""
    top = tmp_path / "sweep"
    if earlier == "users_file":
        (top / "0").mkdir(parents=True)
        (top / "0" / "psf.npy").write_bytes(b"the user's own psf")
    else:
        _run_folder(top / "0", "simulate", "finished", "metrics.json", "sensor.png")
    before = _tree(top)
    proc = _sweep(top)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert _last(proc) == (f"codesign: configuration error: hydra.sweep.dir = '{top / '0'}': {refusal}: "
                           f"{_choose('hydra.sweep.dir')}")
    assert _tree(top) == before and sorted(p.name for p in top.iterdir()) == ["0"]


@pytest.mark.parametrize("record,refusal", [
    ("my own sweep notes\n", "holds files that no codesign sweep wrote (multirun.yaml); a sweep of +experiment=psf "
                             "writes only into an empty folder or its own earlier sweep's, never over files of yours"),
    (None, "holds a sweep of +experiment=simulate (multirun.yaml); a sweep of +experiment=psf never writes into "
           "another experiment's sweep folder"),
], ids=["users_multirun_yaml", "simulate_sweep"])
def test_the_sweeps_own_folder_is_judged_before_hydra_writes_multirun_yaml(tmp_path, record, refusal):
    """The issue's case: the user's own multirun.yaml at the sweep's top was replaced."""
    top = tmp_path / "sweep"
    if record is None:
        _sweep_record(top, "simulate")
    else:
        top.mkdir()
        (top / "multirun.yaml").write_text(record)
    before = _tree(top)
    proc = _sweep(top)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert _last(proc) == (f"codesign: configuration error: hydra.sweep.dir = '{top}': {refusal}: "
                           f"{_choose('hydra.sweep.dir', 'sweep')}")
    assert _tree(top) == before and sorted(p.name for p in top.iterdir()) == ["multirun.yaml"]


def test_a_sweep_with_a_config_error_keeps_a_job_folder_that_held_the_users_log(tmp_path):
    """The issue's case: a sweep with a configuration error deleted a job folder holding only the user's app.log."""
    top = tmp_path / "sweep"
    (top / "0").mkdir(parents=True)
    (top / "0" / "app.log").write_text("the user's log\n")
    proc = _sweep(top, "optics.focal_n=0")
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert _last(proc) == (
        f"codesign: configuration error: hydra.sweep.dir = '{top / '0'}': holds files that no codesign run wrote "
        f"(app.log); +experiment=psf writes only into an empty folder or its own earlier run's, never over files of "
        f"yours: {_choose('hydra.sweep.dir')}")
    assert _tree(top) == {"0/app.log": b"the user's log\n"}


def test_a_link_in_a_job_folder_is_refused_and_not_followed(tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "config.yaml").write_text("the user's config\n")
    top = tmp_path / "sweep"
    _sweep_record(top, "psf")
    job = top / "0"
    job.mkdir()
    (job / STATE).write_text(json.dumps({"task": "psf", "state": "running", "pid": 1}))  # a killed job
    (job / ".hydra").symlink_to(elsewhere)
    proc = _sweep(top)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert _last(proc) == "codesign: configuration error: " + _link_refusal("hydra.sweep.dir", top, "0/.hydra",
                                                                              elsewhere)
    assert _tree(elsewhere) == {"config.yaml": b"the user's config\n"}


def test_a_killed_sweep_of_the_same_experiment_runs_again_in_its_folder(tmp_path):
    top = tmp_path / "sweep"
    _sweep_record(top, "psf")
    _run_folder(top / "0", "psf", "running", "metrics.json")  # killed after its metrics
    proc = _sweep(top)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"codesign: note: hydra.sweep.dir = '{top / '0'}': holds an unfinished +experiment=psf run (killed or " \
           f"stopped before its end); this run replaces its results" in proc.stderr
    assert json.loads((top / "0" / STATE).read_text())["state"] == "finished"
    assert (top / "0" / "psf.npy").is_file() and not (top / "0" / ".codesign.lock").exists()
    # the job's .hydra/ record, written by codesign as the job starts (runstart.write_hydra_record), not by Hydra
    assert sorted(p.name for p in (top / "0" / ".hydra").iterdir()) == ["config.yaml", "hydra.yaml", "overrides.yaml"]
    assert OmegaConf.load(top / "0" / ".hydra" / "overrides.yaml") == ["+experiment=psf", "debug=smoke", "seed=0"]
    assert OmegaConf.load(top / "0" / ".hydra" / "config.yaml").task == "psf"


# ---- links in a single run's folder ----------------------------------------------------------------------------
def test_a_linked_hydra_folder_is_refused_and_its_target_kept(tmp_path):
    """The issue's case: a .hydra linked to a folder elsewhere got its config.yaml, hydra.yaml, overrides.yaml
    rewritten."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "config.yaml").write_text("task: psf\n")
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / STATE).write_text(json.dumps({"task": "psf", "state": "running", "pid": 1}))
    (run_dir / ".hydra").symlink_to(elsewhere)
    proc = run_codesign("+experiment=psf", "debug=smoke", f"hydra.run.dir={run_dir}")
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert _last(proc) == "codesign: configuration error: " + _link_refusal("hydra.run.dir", run_dir, ".hydra",
                                                                              elsewhere)
    assert _tree(elsewhere) == {"config.yaml": b"task: psf\n"}


def test_a_linked_log_is_refused_and_its_target_kept(tmp_path, capsys):
    """The issue's case: a __main__.log linked elsewhere got the run's log appended to the file it points at."""
    target = tmp_path / "notes.txt"
    target.write_text("the user's notes\n")
    run_dir = _run_folder(tmp_path / "run", "psf", "running")
    (run_dir / "__main__.log").symlink_to(target)
    config = OmegaConf.create({"task": "psf", "hydra": {"run": {"dir": str(run_dir)}}})
    with pytest.raises(SystemExit) as info:
        runstart.OutputDirCheck().on_run_start(config)
    assert info.value.code == 2
    assert capsys.readouterr().err == "codesign: configuration error: " + _link_refusal(
        "hydra.run.dir", run_dir, "__main__.log", target) + "\n"
    assert target.read_text() == "the user's notes\n" and not (run_dir / ".codesign.lock").exists()


# ---- a config error's clean-up ---------------------------------------------------------------------------------
def test_a_config_error_never_removes_a_folder_holding_an_older_log(tmp_path, monkeypatch, capsys):
    """A folder no guard recorded (a run started in-process) that held the user's app.log before the run: the
    clean-up after a configuration error removes what the run made, never the user's log nor the folder."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "app.log").write_text("the user's log\n")
    os.utime(run_dir / "app.log", (1e9, 1e9))  # written long before this process
    config_error(monkeypatch, capsys, run_dir, "+experiment=psf", "debug=smoke", "optics.focal_n=0")
    assert _tree(run_dir) == {"app.log": b"the user's log\n"}


# ---- the Python API --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("earlier,refusal", [
    ("users_files", "holds files that no codesign run wrote (phase.png, psf.npy); +experiment=psf writes only into "
                    "an empty folder or its own earlier run's, never over files of yours"),
    ("finished_run", "holds a finished +experiment=psf run (metrics.json, psf.npy); psf does not resume, and a rerun "
                     "would overwrite it"),
    ("users_log", "holds files that no codesign run wrote (app.log); +experiment=psf writes only into an empty "
                  "folder or its own earlier run's, never over files of yours"),
], ids=["users_files", "finished_run", "users_log"])
def test_the_api_refuses_what_the_command_refuses(tmp_path, earlier, refusal):
    """The issue's cases: codesign.run('psf', 'debug=smoke', run_dir=D) overwrote the user's files and a finished
    run, and with a configuration error deleted D when it held only a log."""
    run_dir = tmp_path / "D"
    if earlier == "finished_run":
        _run_folder(run_dir, "psf", "finished", "metrics.json", "psf.npy")
    else:
        run_dir.mkdir()
        for name in {"users_files": ("phase.png", "psf.npy"), "users_log": ("app.log",)}[earlier]:
            (run_dir / name).write_bytes(b"the user's " + name.encode())
    before = _tree(run_dir)
    typo = ("optics.focal_n=0",) if earlier == "users_log" else ()
    with pytest.raises(ConfigError) as info:
        codesign.run("psf", "debug=smoke", *typo, run_dir=run_dir)
    assert str(info.value) == f"run_dir = '{run_dir}': {refusal}: {_choose('run_dir')}"
    assert _tree(run_dir) == before and not runlock.HELD


def test_the_api_continues_its_own_killed_run_and_frees_the_folder(tmp_path, monkeypatch, capsys):
    """A run of the API has no .hydra/: its completion marker names its experiment (same rules as the command)."""
    run_dir = tmp_path / "D"
    run_dir.mkdir()
    (run_dir / "metrics.json").write_text("{}\n")
    (run_dir / STATE).write_text(json.dumps({"task": "psf", "state": "running", "pid": 1}))
    stop_before_work(monkeypatch)
    with pytest.raises(WorkStarted):
        codesign.run("psf", "debug=smoke", run_dir=run_dir)
    assert f"codesign: note: run_dir = '{run_dir.absolute()}': holds an unfinished +experiment=psf run (killed or " \
           f"stopped before its end); this run replaces its results" in capsys.readouterr().err
    assert not runlock.HELD and not (run_dir / ".codesign.lock").exists()  # free for the next process


# ---- torchrun: rank 0 guards, the other ranks wait -------------------------------------------------------------
@pytest.mark.parametrize("rank", [0, 1])
def test_under_torchrun_rank_0_guards_the_folder(tmp_path, monkeypatch, capsys, rank):
    run_dir = tmp_path / "mine"
    run_dir.mkdir()
    (run_dir / "psf.npy").write_bytes(b"the user's own psf")
    monkeypatch.setattr(distributed, "current", lambda: distributed.DistContext(rank, 2, rank))
    sent = []
    monkeypatch.setattr(distributed, "broadcast_flag", lambda flag, ctx: sent.append(flag) or False)  # refused
    config = OmegaConf.create({"task": "baseline", "hydra": {"run": {"dir": str(run_dir)}}})
    if rank == 1:  # writes nothing, judges nothing: rank 0 has, and its verdict stops this rank before its Hydra
        with pytest.raises(SystemExit) as info:  # creates anything there (no <job>.rank1.log in the user's folder)
            runstart.OutputDirCheck().on_run_start(config)
        assert info.value.code == 2 and capsys.readouterr().err == ""
        assert sorted(p.name for p in run_dir.iterdir()) == ["psf.npy"] and not runlock.HELD
        return
    with pytest.raises(SystemExit):
        runstart.OutputDirCheck().on_run_start(config)
    assert capsys.readouterr().err.startswith(f"codesign: configuration error: hydra.run.dir = '{run_dir}': holds "
                                              f"files that no codesign run wrote (psf.npy)")
    assert sent == [False]  # rank 0 told the other ranks before it stopped


# ---- resumes ----------------------------------------------------------------------------------------------------
def test_a_resume_with_fewer_steps_than_the_checkpoint_is_refused(trained, tmp_path):
    """The issue's case: a checkpoint at step 13 resumed with trainer.steps=6 reported 13 steps with no note."""
    cfg = tiny_cfg()
    loaded = []
    trainer = SimpleNamespace(model=build_model(cfg), step=0, spec=SimpleNamespace(steps=6),
                              dist=distributed.SINGLE, load_state_dict=loaded.append)
    state = {**copy.deepcopy(trained), "step": 13, "opt_g": {}, "opt_d": {}, "sched_g": {}, "sched_d": {}, "rng": {}}
    path = save_checkpoint(tmp_path / "run" / "checkpoint.pt", state)
    with pytest.raises(ConfigError) as info:
        resume_if_possible(trainer, cfg, tmp_path / "run")
    assert str(info.value) == (f"trainer.steps = 6: is fewer than the 13 steps already trained in the checkpoint it "
                               f"resumes ({path}): a resume trains on up to trainer.steps, never back: set "
                               f"trainer.steps=13 or more, or start a new run directory")
    assert loaded == []
    trainer.spec.steps = 13  # as many: the training is complete, nothing to undo
    resume_if_possible(trainer, cfg, tmp_path / "run")
    assert len(loaded) == 1


def _finished_baseline(run_dir: Path, *overrides: str) -> Path:
    """A finished baseline's folder, its .hydra/config.yaml as Hydra records the composed config of ``overrides``."""
    _run_folder(run_dir, "baseline", "finished", "metrics.json", "checkpoint.pt")
    recorded = compose_cfg("+experiment=baseline", "debug=smoke", *overrides)
    (run_dir / ".hydra" / "config.yaml").write_text(OmegaConf.to_yaml(recorded))
    return run_dir


def test_a_finished_baseline_is_not_rewritten_with_other_evaluate_settings(tmp_path):
    """The issue's case: baseline rerun on its finished folder with another evaluate.laser_strengths silently
    replaced its metrics.json (the old figures gone, the old panels left beside it)."""
    run_dir = _finished_baseline(tmp_path / "run", "evaluate.laser_strengths=[0,1000]")
    before = _tree(run_dir)
    proc = run_codesign("+experiment=baseline", "debug=smoke", f"hydra.run.dir={run_dir}")
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert _last(proc) == (
        f"codesign: configuration error: hydra.run.dir = '{run_dir}': holds a finished +experiment=baseline run "
        f"(metrics.json, checkpoint.pt) that was trained with different evaluate.laser_strengths: "
        f"evaluate.laser_strengths = [0, 1000] there, [0.0, 10.0, 100.0, 1000.0, 10000.0, 100000.0, 1000000.0] here; "
        f"a finished run is never rewritten in place (to evaluate it otherwise: +experiment=evaluate "
        f"checkpoint={run_dir / 'checkpoint.pt'}): {_choose('hydra.run.dir')}")
    assert _tree(run_dir) == before


def test_a_finished_training_run_runs_again_in_place_only_with_its_own_settings(tmp_path):
    run_dir = _finished_baseline(tmp_path / "run")
    same = compose_cfg("+experiment=baseline", "debug=smoke")
    assert rundir.check_earlier_run(run_dir, "baseline", config=same) == (
        f"hydra.run.dir = '{run_dir}': holds a finished +experiment=baseline run made with these same settings: it "
        f"is run again in place, its checkpoint and finished parts reused")
    (run_dir / ".hydra" / "config.yaml").unlink()  # as the API's runs leave it: no record of the settings
    with pytest.raises(ConfigError) as info:
        rundir.check_earlier_run(run_dir, "baseline", "run_dir", config=same)
    assert str(info.value) == (
        f"run_dir = '{run_dir}': holds a finished +experiment=baseline run (metrics.json, checkpoint.pt) whose "
        f"settings cannot be compared with this run's (no readable .hydra/config.yaml there); a finished run is never "
        f"rewritten in place (to evaluate it otherwise: +experiment=evaluate checkpoint={run_dir / 'checkpoint.pt'}): "
        f"{_choose('run_dir')}")


# ---- files opened without following a link ----------------------------------------------------------------------
def test_a_linked_lock_file_is_refused_and_its_target_kept(tmp_path, capsys):
    """The lock is opened (and truncated) before the folder is judged: a .codesign.lock linked to the user's file
    must neither truncate it nor be written through."""
    target = tmp_path / "thesis.tex"
    target.write_text("the user's thesis\n")
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / ".codesign.lock").symlink_to(target)
    config = OmegaConf.create({"task": "psf", "hydra": {"run": {"dir": str(run_dir)}}})
    with pytest.raises(SystemExit):
        runstart.OutputDirCheck().on_run_start(config)
    assert capsys.readouterr().err == "codesign: configuration error: " + _link_refusal(
        "hydra.run.dir", run_dir, ".codesign.lock", target) + "\n"
    assert target.read_text() == "the user's thesis\n" and (run_dir / ".codesign.lock").is_symlink()


def test_the_run_log_is_never_appended_through_a_link(tmp_path):
    """Hydra's job log (conf/config.yaml: hydra.job_logging's file handler) opens its file without following a
    link swapped in after the folder was guarded; a plain file is appended to as before."""
    from codesign.io.logfile import NoFollowFileHandler

    target = tmp_path / "notes.txt"
    target.write_text("the user's notes\n")
    (tmp_path / "__main__.log").symlink_to(target)
    with pytest.raises(OSError):
        NoFollowFileHandler(str(tmp_path / "__main__.log"))
    assert target.read_text() == "the user's notes\n"
    plain = tmp_path / "plain.log"
    plain.write_text("earlier line\n")
    handler = NoFollowFileHandler(str(plain))
    handler.emit(logging.LogRecord("codesign", logging.INFO, __file__, 1, "a new line", None, None))
    handler.close()
    assert plain.read_text() == "earlier line\na new line\n"
    conf = OmegaConf.load(CONF_DIR / "config.yaml")  # the handler Hydra's job log is made with
    assert conf.hydra.job_logging.handlers.file["class"] == "codesign.io.logfile.NoFollowFileHandler"


HOLD = """
import fcntl, json, os, sys, time
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)
fcntl.flock(fd, fcntl.LOCK_EX)
os.write(fd, json.dumps({"pid": os.getpid(), "task": "psf"}).encode())
print("held", flush=True)
time.sleep(60)
"""


def test_a_job_folder_made_in_use_after_the_sweep_started_is_refused(tmp_path, capsys):
    """A job's folder that did not exist when the sweep was guarded is locked as the job starts (Hydra's
    on_job_start): a run that took it meanwhile is named, as for the single command."""
    job = tmp_path / "sweep" / "1"
    job.mkdir(parents=True)
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(job / ".codesign.lock")], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        config = OmegaConf.create({"task": "psf", "hydra": {"mode": RunMode.MULTIRUN,
                                                            "runtime": {"output_dir": str(job)}}})
        with pytest.raises(SystemExit) as info:
            runstart.OutputDirCheck().on_job_start(config)
    finally:
        holder.kill()
        holder.wait()
    assert info.value.code == 2
    assert capsys.readouterr().err == (
        f"codesign: configuration error: hydra.sweep.dir = '{job}': is in use by a running +experiment=psf run (PID "
        f"{holder.pid}): two runs never share a folder (each would overwrite the other's results): wait for it to "
        f"end, or {_choose('hydra.sweep.dir')}\n")


def test_a_single_runs_folder_is_locked_in_on_run_start_not_as_its_job_starts(tmp_path, monkeypatch):
    single = _hydra_job(tmp_path / "run", monkeypatch)
    runstart.OutputDirCheck().on_job_start(single)  # a single run's folder was locked in on_run_start already
    assert not runlock.HELD and (tmp_path / "run" / ".hydra" / "config.yaml").is_file()


def _hydra_job(run_dir: Path, monkeypatch):
    """The config Hydra's run_job hands its callbacks for a single run into ``run_dir`` (made), set as Hydra's."""
    from hydra import compose, initialize_config_dir
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import open_dict, read_write

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        config = compose("config", overrides=["+experiment=psf", "debug=smoke"], return_hydra_config=True)
    with read_write(config.hydra.runtime), open_dict(config.hydra.runtime):
        config.hydra.runtime.output_dir = str(run_dir)
    monkeypatch.setattr(HydraConfig.instance(), "cfg", None)  # Hydra's global config put back after the test
    HydraConfig.instance().set_config(config)
    run_dir.mkdir()
    return config


def test_the_run_records_its_config_as_hydra_would_without_following_a_link(tmp_path, monkeypatch, capsys):
    """Hydra wrote .hydra/config.yaml, hydra.yaml and overrides.yaml with a plain open, after the guard: a link
    swapped in meanwhile was followed. hydra.output_subdir is off; codesign writes the same three files as the job
    starts, never through a link."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.core.utils import _save_config  # Hydra's own writer: the content to match
    from omegaconf import open_dict, read_write

    assert OmegaConf.load(CONF_DIR / "config.yaml").hydra.output_subdir is None
    run_dir = tmp_path / "run"
    config = _hydra_job(run_dir, monkeypatch)
    runstart.OutputDirCheck().on_job_start(config)
    task_cfg = copy.deepcopy(config)
    with read_write(task_cfg), open_dict(task_cfg):
        del task_cfg["hydra"]
    for name, node in (("config.yaml", task_cfg), ("hydra.yaml", HydraConfig.instance().cfg),
                       ("overrides.yaml", config.hydra.overrides.task)):
        _save_config(node, name, tmp_path / "by_hydra")
        assert (run_dir / ".hydra" / name).read_text() == (tmp_path / "by_hydra" / name).read_text(), name
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "config.yaml").write_text("the user's config\n")
    shutil.rmtree(run_dir / ".hydra")
    for linked, target in ((".hydra", elsewhere), (".hydra/config.yaml", elsewhere / "config.yaml")):
        if linked != ".hydra":  # the folder real again, its config.yaml a link
            (run_dir / ".hydra").unlink()
            (run_dir / ".hydra").mkdir()
        (run_dir / linked).symlink_to(target)  # swapped in after the guard
        with pytest.raises(SystemExit) as info:
            runstart.OutputDirCheck().on_job_start(config)
        assert info.value.code == 2
        assert capsys.readouterr().err == (
            f"codesign: configuration error: hydra.run.dir = '{run_dir}': .hydra/config.yaml (or .hydra) became a "
            f"symbolic link after the folder was checked; a run never writes through a link (it would change files "
            f"outside its folder): remove the link, or choose another folder with hydra.run.dir=PATH\n")
        assert _tree(elsewhere) == {"config.yaml": b"the user's config\n"}, linked
