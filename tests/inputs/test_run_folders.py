"""Run folders that cannot lose anything (issue 38): a folder of the user's own files is refused untouched; a lock
keeps a second run out of a folder in use (a killed run's stale lock is taken over with a note); a completion
marker written last tells a finished run from a killed one, and the temp files of a killed write are removed by
the next run in the folder."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

import codesign.experiments as experiments
from codesign.errors import ConfigError, OutputWriteError
from codesign.experiments import rundir, runlock, runstart
from tests.inputs._run import fresh_run_folder_state  # noqa: F401 (autouse: the guard's records, fresh per test)
from codesign.io import files as io
from tests.cli import run_codesign
from tests.conftest import REPO_ROOT
from tests.inputs._run import compose_cfg, config_error

CHOOSE = "choose another folder with hydra.run.dir=PATH (or leave hydra.run.dir unset: every run gets a new one)"
LOCK, STATE = ".codesign.lock", ".codesign-run.json"


def _tree(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _recorded(run_dir: Path, task: str) -> None:
    """What Hydra writes for a run of ``task`` before our code starts: its recorded config."""
    (run_dir / ".hydra").mkdir(parents=True, exist_ok=True)
    (run_dir / ".hydra" / "config.yaml").write_text(f"task: {task}\nseed: 0\n")


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid




# ---- a folder of the user's own files -------------------------------------------------------------------------
def test_a_folder_of_the_users_own_files_is_refused_untouched(tmp_path):
    """The issue's case: `psf` into a folder holding the user's psf.npy and phase.png (no metrics.json) replaced
    both, exit 0."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "psf.npy").write_bytes(b"the user's own psf")
    (mine / "phase.png").write_bytes(b"the user's own figure")
    (mine / ".notes").write_text("hidden, still theirs\n")
    before = _tree(mine)
    proc = run_codesign("+experiment=psf", "debug=smoke", f"hydra.run.dir={mine}")
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1] == (
        f"codesign: configuration error: hydra.run.dir = '{mine}': holds files that no codesign run wrote (.notes, "
        f"phase.png, psf.npy); +experiment=psf writes only into an empty folder or its own earlier run's, never "
        f"over files of yours: {CHOOSE}")
    assert _tree(mine) == before and sorted(p.name for p in mine.iterdir()) == [".notes", "phase.png", "psf.npy"]


# ---- two runs, one folder: the lock ---------------------------------------------------------------------------
def _hold_the_folder(run_dir: Path):
    """A first run in a forked child: the Hydra callback's start on ``run_dir``, then it keeps running until the
    returned pipe closes. Returns (its PID, the pipe's write end)."""
    ready_r, ready_w = os.pipe()
    stop_r, stop_w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns into pytest
        code = 1
        try:
            os.close(ready_r)
            os.close(stop_w)
            config = OmegaConf.create({"task": "psf", "hydra": {"run": {"dir": str(run_dir)}}})
            runstart.OutputDirCheck().on_run_start(config)
            os.write(ready_w, b"started")
            os.read(stop_r, 1)  # running, until the parent closes the pipe
            code = 0
        finally:
            os._exit(code)
    os.close(ready_w)
    os.close(stop_r)
    assert os.read(ready_r, 16) == b"started"
    os.close(ready_r)
    return pid, stop_w


def test_a_second_run_on_a_folder_in_use_is_refused_naming_the_first_pid(tmp_path):
    """The issue's case: two runs started together on one folder both reported success; only one run's results
    remained."""
    run_dir = tmp_path / "run"
    pid, stop = _hold_the_folder(run_dir)
    try:
        before = _tree(run_dir)
        proc = run_codesign("+experiment=psf", "debug=smoke", f"hydra.run.dir={run_dir}")
    finally:
        os.close(stop)
        os.waitpid(pid, 0)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1] == (
        f"codesign: configuration error: hydra.run.dir = '{run_dir}': is in use by a running +experiment=psf run "
        f"(PID {pid}): two runs never share a folder (each would overwrite the other's results): wait for it to "
        f"end, or {CHOOSE}")
    assert _tree(run_dir) == before  # the first run's folder: nothing of the second's


def test_a_stale_lock_of_a_killed_run_is_taken_over_with_a_note(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    dead = _dead_pid()
    stale = json.dumps({"pid": dead, "task": "psf"}) + "\n"
    (run_dir / LOCK).write_text(stale)  # a run killed before Hydra wrote anything: its lock alone
    config = OmegaConf.create({"task": "psf", "hydra": {"run": {"dir": str(run_dir)}}})
    runstart.OutputDirCheck().on_run_start(config)
    assert capsys.readouterr().err == (f"codesign: note: hydra.run.dir = '{run_dir}': the lock of PID {dead} "
                                       f"(+experiment=psf), which no longer runs, is taken over: that run was killed\n")
    assert json.loads((run_dir / LOCK).read_text()) == {"pid": os.getpid(), "task": "psf"}
    # this run then stops on a configuration error: the folder as it was, the stale lock included
    config_error(monkeypatch, capsys, run_dir, "+experiment=psf", "debug=smoke", "optics.focal_n=0")
    assert _tree(run_dir) == {LOCK: stale.encode()}


# ---- finished or killed: the completion marker ---------------------------------------------------------------
KILLED_AFTER_METRICS = """
import os, signal, sys
from pathlib import Path
import codesign.experiments as experiments
from codesign.config import resolvers
from codesign.io import files as io
from tests.inputs._run import compose_cfg

def task(cfg, run_dir, device):  # mask_search writes metrics.json, then its figures: SIGKILL during mtf.png
    io.write_json(run_dir / "metrics.json", {"v": 1})
    io._atomic(run_dir / "mtf.png", lambda tmp: os.kill(os.getpid(), signal.SIGKILL), ".png")

resolvers.register()
experiments.experiment_function = lambda name: task
experiments.run_experiment(compose_cfg("+experiment=mask_search", "debug=smoke"), run_dir=Path(sys.argv[1]))
"""


def _rerun(monkeypatch, run_dir: Path, task: str, outputs: tuple[str, ...]) -> None:
    """A successful run of ``task`` in ``run_dir`` (in process, its work replaced by writing ``outputs``)."""
    def work(cfg, run_dir, device):
        for name in outputs:
            io.atomic_write_bytes(run_dir / name, lambda f: f.write(b"rerun"))

    monkeypatch.setattr(experiments, "experiment_function", lambda name: work)
    experiments.run_experiment(compose_cfg(f"+experiment={task}", "debug=smoke"), run_dir=run_dir)


def test_a_run_killed_after_its_metrics_is_unfinished_and_may_run_again(tmp_path, monkeypatch):
    """The issue's case: a SIGKILL during mask_search's figures left metrics.json and a temp file, and the rerun
    was refused as "a finished run"."""
    run_dir = tmp_path / "run"
    _recorded(run_dir, "mask_search")
    killed = subprocess.run([sys.executable, "-c", KILLED_AFTER_METRICS, str(run_dir)], cwd=REPO_ROOT,
                            capture_output=True, text=True, timeout=120)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]
    temps = [p.name for p in run_dir.iterdir() if p.name.endswith(".tmp")]
    assert (run_dir / "metrics.json").is_file() and len(temps) == 1 and not (run_dir / "mtf.png").exists()
    assert rundir.check_earlier_run(run_dir, "mask_search") == (
        f"hydra.run.dir = '{run_dir}': holds an unfinished +experiment=mask_search run (killed or stopped before its "
        f"end); this run replaces its results")
    _rerun(monkeypatch, run_dir, "mask_search", ("metrics.json", "mtf.png"))
    assert not [p.name for p in run_dir.iterdir() if p.name.endswith(".tmp")]  # the killed write's temp removed
    with pytest.raises(ConfigError, match=r"holds a finished \+experiment=mask_search run \(metrics.json, mtf.png\)"):
        rundir.check_earlier_run(run_dir, "mask_search")


@pytest.mark.parametrize("marker", [{"task": "export", "state": "running", "pid": 1}, None],
                         ids=["killed_run", "killed_run_of_an_earlier_version"])
def test_the_temp_file_of_a_killed_write_does_not_survive_the_rerun(tmp_path, monkeypatch, marker):
    """The issue's case: a SIGKILL during export left a 656 KB .height.*.png.tmp that survived a successful rerun."""
    run_dir = tmp_path / "run"
    _recorded(run_dir, "export")
    (run_dir / "metrics.json").write_text('{"v": 1}\n')
    (run_dir / "height_m.npy").write_bytes(b"killed run")
    (run_dir / ".height.k2j_x9ab.png.tmp").write_bytes(b"\0" * 656_000)
    (run_dir / "hparams").mkdir()
    (run_dir / "hparams" / ".events.abcd1234.tmp").write_bytes(b"partial")
    if marker is not None:
        (run_dir / STATE).write_text(json.dumps(marker))
    why = "killed or stopped before its end" if marker else "killed during a write: 2 temp file(s) left"
    assert rundir.check_earlier_run(run_dir, "export") == (
        f"hydra.run.dir = '{run_dir}': holds an unfinished +experiment=export run ({why}); this run replaces its "
        f"results")
    _rerun(monkeypatch, run_dir, "export", ("height_m.npy", "height.png", "metrics.json"))
    assert io.leftover_temps(run_dir) == []
    assert (run_dir / "height.png").read_bytes() == b"rerun"


@pytest.mark.parametrize("earlier,refused", [
    ({STATE: {"task": "psf", "state": "finished", "pid": 1}}, True),  # finished, no metrics.json of its own
    ({STATE: {"task": "psf", "state": "running", "pid": 1}, "metrics.json": {"v": 1}}, False),  # killed after it
], ids=["marker_finished_without_metrics", "marker_running_with_metrics"])
def test_a_finished_run_is_told_by_its_completion_marker(tmp_path, earlier, refused):
    run_dir = tmp_path / "run"
    _recorded(run_dir, "psf")
    for name, content in earlier.items():
        (run_dir / name).write_text(json.dumps(content))
    if refused:
        with pytest.raises(ConfigError, match=r"holds a finished \+experiment=psf run "):
            rundir.check_earlier_run(run_dir, "psf")
    else:
        assert "holds an unfinished +experiment=psf run" in rundir.check_earlier_run(run_dir, "psf")


def test_the_completion_marker_is_the_runs_last_write(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    seen = []

    def work(cfg, run_dir, device):
        seen.append(json.loads((run_dir / STATE).read_text())["state"])  # during the work: not finished
        io.write_json(run_dir / "metrics.json", {"v": 1})

    monkeypatch.setattr(experiments, "experiment_function", lambda name: work)
    experiments.run_experiment(compose_cfg("+experiment=psf", "debug=smoke"), run_dir=run_dir)
    assert seen == ["running"]
    assert json.loads((run_dir / STATE).read_text()) == {"task": "psf", "state": "finished", "pid": os.getpid()}

    def fails(cfg, run_dir, device):  # a run that ends in an error is not finished either
        io.write_json(run_dir / "metrics.json", {"v": 2})
        raise OutputWriteError("cannot write mtf.png")

    monkeypatch.setattr(experiments, "experiment_function", lambda name: fails)
    with pytest.raises(SystemExit):
        experiments.run_experiment(compose_cfg("+experiment=psf", "debug=smoke"), run_dir=run_dir)
    assert json.loads((run_dir / STATE).read_text())["state"] == "running"


# ---- the whole path: a real mask_search killed during its figures, then run again -------------------------------
KILL_DURING = """
import os, runpy, signal, sys
from codesign.io import files
fsync, name = files._fsync, sys.argv.pop(1)

def fsync_then_kill(tmp):  # the data written, the rename not yet done
    fsync(tmp)
    if os.path.basename(tmp).startswith("." + name + "."):
        os.kill(os.getpid(), signal.SIGKILL)

files._fsync = fsync_then_kill
sys.argv = ["codesign", *sys.argv[1:]]
runpy.run_module("codesign", run_name="__main__", alter_sys=True)
"""


@pytest.mark.slow  # 15 s: a killed and a full mask_search smoke run; the fast twin: the in-process tests above
def test_mask_search_killed_during_its_figures_runs_again_in_its_folder(tmp_path):
    run_dir = tmp_path / "run"
    args = ["+experiment=mask_search", "debug=smoke", "threads=1", f"hydra.run.dir={run_dir}"]
    env = {**os.environ, "OMP_NUM_THREADS": "2", "MKL_NUM_THREADS": "2"}
    killed = subprocess.Popen([sys.executable, "-c", KILL_DURING, "mtf", *args], cwd=REPO_ROOT, env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    err = killed.communicate(timeout=300)[1]
    assert killed.returncode == -signal.SIGKILL, err[-2000:]
    assert (run_dir / "metrics.json").is_file() and [p for p in run_dir.iterdir() if p.name.endswith(".png.tmp")]
    again = run_codesign(*args, timeout=300)
    assert again.returncode == 0, again.stderr[-3000:]
    notes = [line for line in again.stderr.splitlines() if line.startswith("codesign: note: ")]
    assert notes == [f"codesign: note: hydra.run.dir = '{run_dir}': the lock of PID {killed.pid} "
                     f"(+experiment=mask_search), which no longer runs, is taken over: that run was killed",
                     f"codesign: note: hydra.run.dir = '{run_dir}': holds an unfinished +experiment=mask_search run "
                     f"(killed or stopped before its end); this run replaces its results"]
    assert (run_dir / "mtf.png").is_file() and (run_dir / "pareto.png").is_file()
    assert io.leftover_temps(run_dir) == [] and not (run_dir / LOCK).exists()
    assert json.loads((run_dir / STATE).read_text())["state"] == "finished"

