"""The output directory: every result file is written atomically (a write that fails half-way leaves the earlier
file intact and no temp file), an unwritable run dir is refused before any work, and a refused run never deletes
or rewrites what an earlier run left in its folder."""
from __future__ import annotations

import errno
import json
import os
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

import codesign.experiments as experiments
from codesign.io import files as io
from codesign.experiments import rundir, runstart
from codesign.train.checkpoint import save_checkpoint
from codesign.train.evaluation import write_csv
from codesign.io.captures import save_png16
from codesign.errors import ConfigError, OutputWriteError
from tests.cli import run_codesign
from tests.inputs._run import config_error


def _raise(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def _half_then_full_disk(*args, **kwargs):
    """A writer (torch.save, np.save, Figure.savefig) that writes part of its file, then fails as a full disk."""
    target = next(a for a in args if hasattr(a, "write") or isinstance(a, (str, os.PathLike)))
    if hasattr(target, "write"):
        target.write(b"partial")
    else:
        with open(target, "wb") as f:
            f.write(b"partial")
    _raise()


def _figure(v: int):
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(1, 1))
    fig.text(0.5, 0.5, str(v))
    return fig


def _png_value(p) -> int:
    from PIL import Image

    with Image.open(p) as img:
        return int(np.asarray(img)[0, 0])


# file name -> (write(path, version), read(path) -> version, break(monkeypatch): how the write fails)
WRITERS = {
    "metrics.json": (lambda p, v: io.write_json(p, {"v": v}), lambda p: json.loads(p.read_text())["v"],
                     lambda mp: mp.setattr(io.json, "dump", lambda obj, f, **kw: (f.write('{"v": 9'), _raise()))),
    "checkpoint.pt": (lambda p, v: save_checkpoint(p, {"model": {}, "config": {}, "v": torch.tensor(v)}),
                      lambda p: int(torch.load(p, weights_only=True)["v"]),
                      lambda mp: mp.setattr(torch, "save", _half_then_full_disk)),
    "array.npy": (lambda p, v: io.save_npy(p, np.full(3, v)), lambda p: int(np.load(p)[0]),
                  lambda mp: mp.setattr(io.np, "save", _half_then_full_disk)),
    "evaluation.csv": (lambda p, v: write_csv(p, [{"v": v}]), lambda p: int(p.read_text().split()[1]),
                       lambda mp: mp.setattr(io, "_fsync", _raise)),  # written, not yet on disk
    "restored_a.png": (lambda p, v: save_png16(p, np.full((4, 4), v / 65535.0), scale=65535.0), _png_value,
                       lambda mp: mp.setattr(io.os, "replace", _raise)),  # the rename itself fails
    "figure.png": (lambda p, v: io.save_figure(p, _figure(v)), lambda p: 1,
                   lambda mp: mp.setattr("matplotlib.figure.Figure.savefig", _half_then_full_disk)),
}


@pytest.mark.parametrize("name", sorted(WRITERS))
def test_a_write_failing_half_way_keeps_the_earlier_file_and_leaves_no_temp(tmp_path, monkeypatch, name):
    write, read, break_it = WRITERS[name]
    path = tmp_path / name
    write(path, 1)
    before = path.read_bytes()
    break_it(monkeypatch)
    with pytest.raises(OutputWriteError, match="^cannot write " + re.escape(str(path)) + r" \(OSError: No space "
                       r"left on device\); an earlier " + re.escape(name) + ", if any, is unchanged$"):
        write(path, 2)
    assert path.read_bytes() == before and read(path) == 1
    assert os.listdir(tmp_path) == [name]  # no .name.*.tmp left behind


def test_a_failing_writer_that_is_not_io_keeps_its_own_error(tmp_path):
    io.write_json(tmp_path / "m.json", {"v": 1})
    with pytest.raises(TypeError):
        io.write_json(tmp_path / "m.json", {"v": object()})  # not JSON-serializable
    assert json.loads((tmp_path / "m.json").read_text()) == {"v": 1} and os.listdir(tmp_path) == ["m.json"]


# ---- an unwritable output folder --------------------------------------------------------------------------
def test_output_folder_below_a_file(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(ConfigError, match="^hydra.run.dir = " + re.escape(repr(str(tmp_path / "file" / "run"))) +
                       ": cannot be created: " + re.escape(str(tmp_path / "file")) + " is a file, not a folder; "
                       r"choose another output folder with hydra.run.dir=PATH$"):
        io.check_writable_dir(tmp_path / "file" / "run")


def test_output_folder_that_refuses_new_files(tmp_path, monkeypatch):
    # what a read-only mount or a folder of another user does, simulated so that it also holds for root
    def refuse(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied")
    monkeypatch.setattr(io.tempfile, "mkstemp", refuse)
    with pytest.raises(ConfigError, match="^hydra.run.dir = " + re.escape(repr(str(tmp_path / "run"))) + r": is not "
                       r"writable \(PermissionError: Permission denied in " + re.escape(str(tmp_path)) + r"\): choose "
                       r"a writable output folder with hydra.run.dir=PATH$"):
        io.check_writable_dir(tmp_path / "run")


def _as_unprivileged_user(fn) -> str:
    """``fn()`` in a forked child that runs as a user whom the mode bits bind (root drops to nobody, 65534; another
    user stays itself); returns what it printed: the ConfigError's message, or "no error"."""
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns into pytest
        code = 1
        try:
            os.close(read)
            if os.geteuid() == 0:
                os.setgroups([])
                os.setgid(65534)
                os.setuid(65534)
            try:
                fn()
                said = "no error"
            except ConfigError as err:
                said = str(err)
            os.write(write, said.encode())
            code = 0
        finally:
            os._exit(code)
    os.close(write)
    with os.fdopen(read) as f:
        said = f.read()
    assert os.waitpid(pid, 0)[1] == 0, "the child failed before it could answer"
    return said


def test_read_only_folder_by_permissions():
    """A folder whose mode forbids writing, checked by a user the mode binds (as root, CI's user, the check runs as
    nobody: root itself ignores the mode bits, and tests/inputs must fail where they run)."""
    base = Path(tempfile.mkdtemp(prefix="codesign-ro-"))
    try:
        base.chmod(0o755)  # the unprivileged user may enter it
        ro = base / "ro"
        ro.mkdir(mode=0o555)
        ro.chmod(0o555)
        said = _as_unprivileged_user(lambda: io.check_writable_dir(ro / "run"))
        assert re.match(r"^hydra.run.dir = .*: is not writable \(PermissionError: Permission denied in "
                        + re.escape(str(ro)) + r"\): choose a writable output folder", said), said
        ok = base / "ok"
        ok.mkdir(mode=0o777)
        ok.chmod(0o777)
        assert _as_unprivileged_user(lambda: io.check_writable_dir(ok / "run")) == "no error"
    finally:
        for d in (base / "ro", base / "ok"):
            if d.exists():
                d.chmod(0o755)
        shutil.rmtree(base, ignore_errors=True)


def test_unwritable_run_dir_stops_before_any_work(tmp_path, monkeypatch, capsys):
    (tmp_path / "file").write_text("x")
    run_dir = tmp_path / "file" / "run"
    line = config_error(monkeypatch, capsys, run_dir, "+experiment=baseline", "debug=smoke")
    assert line == (f"codesign: configuration error: hydra.run.dir = '{run_dir}': cannot be created: "
                    f"{tmp_path / 'file'} is a file, not a folder; choose another output folder with "
                    f"hydra.run.dir=PATH")


def test_hydra_callback_refuses_before_hydra_creates_the_dir(tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    config = OmegaConf.create({"hydra": {"run": {"dir": str(tmp_path / "file" / "run")}}})
    with pytest.raises(SystemExit) as info:
        runstart.OutputDirCheck().on_run_start(config)
    assert info.value.code == 2
    assert capsys.readouterr().err.startswith("codesign: configuration error: hydra.run.dir = ")


def test_cli_unwritable_output_dir_exits_2_without_traceback(tmp_path):
    (tmp_path / "file").write_text("x")
    run_dir = tmp_path / "file" / "run"
    proc = run_codesign("+experiment=psf", "debug=smoke", f"hydra.run.dir={run_dir}")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1] == (
        f"codesign: configuration error: hydra.run.dir = '{run_dir}': cannot be created: {tmp_path / 'file'} is a "
        f"file, not a folder; choose another output folder with hydra.run.dir=PATH")
    assert "Traceback" not in proc.stderr


def test_a_write_failing_during_a_run_exits_1_naming_the_file(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "run"

    def task(cfg, run_dir, device):
        io.write_json(run_dir / "metrics.json", {"v": 1})
        monkeypatch.setattr(io.os, "replace", _raise)
        io.write_json(run_dir / "metrics.json", {"v": 2})

    monkeypatch.setattr(experiments, "experiment_function", lambda name: task)
    cfg = OmegaConf.create({"task": "psf"})
    with pytest.raises(SystemExit) as info:
        experiments.run_experiment(cfg, run_dir=run_dir)
    assert info.value.code == 1
    assert capsys.readouterr().err.strip() == (f"codesign: output error: cannot write {run_dir / 'metrics.json'} "
                                               f"(OSError: No space left on device); an earlier metrics.json, if "
                                               f"any, is unchanged")
    assert json.loads((run_dir / "metrics.json").read_text()) == {"v": 1}


# ---- an earlier run's folder --------------------------------------------------------------------------------
def test_a_refused_rerun_keeps_the_earlier_run_and_its_recorded_config(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "run"  # an earlier run: its config, log and results
    (run_dir / ".hydra").mkdir(parents=True)
    (run_dir / ".hydra" / "config.yaml").write_text("earlier: config\n")
    (run_dir / "__main__.log").write_text("earlier log\n")
    monkeypatch.setattr(rundir, "EARLIER", {})
    rundir.remember(run_dir)  # what the Hydra callback does before Hydra rewrites .hydra/
    (run_dir / ".hydra" / "config.yaml").write_text("refused: config\n")
    line = config_error(monkeypatch, capsys, run_dir, "+experiment=psf", "debug=smoke", "optics.focal_n=0")
    assert line.startswith("codesign: configuration error: optics.focal_n = 0")
    assert (run_dir / ".hydra" / "config.yaml").read_text() == "earlier: config\n"
    assert (run_dir / "__main__.log").read_text() == "earlier log\n"
    assert sorted(p.name for p in run_dir.iterdir()) == [".hydra", "__main__.log"]


def test_a_refused_run_in_a_folder_of_the_users_keeps_it_as_it_was(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "mine"  # an existing folder that was never a run dir
    run_dir.mkdir()
    (run_dir / "notes.txt").write_text("keep me\n")
    monkeypatch.setattr(rundir, "EARLIER", {})
    rundir.remember(run_dir)
    (run_dir / ".hydra").mkdir()  # what Hydra adds for the refused run
    (run_dir / ".hydra" / "config.yaml").write_text("refused: config\n")
    config_error(monkeypatch, capsys, run_dir, "+experiment=psf", "debug=smoke", "optics.focal_n=0")
    assert sorted(p.name for p in run_dir.iterdir()) == ["notes.txt"]
    assert (run_dir / "notes.txt").read_text() == "keep me\n"


def _earlier_run(run_dir, task: str):
    """A folder as a finished run of ``task`` leaves it: its recorded config, log and results."""
    (run_dir / ".hydra").mkdir(parents=True)
    (run_dir / ".hydra" / "config.yaml").write_text(f"task: {task}\nseed: 0\n")
    (run_dir / "__main__.log").write_text("earlier log\n")
    (run_dir / "metrics.json").write_text('{"v": 1}\n')
    (run_dir / "mtf.png").write_bytes(b"png")


def _tree(folder) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


CHOOSE = "choose another folder with hydra.run.dir=PATH (or leave hydra.run.dir unset: every run gets a new one)"


@pytest.mark.parametrize("args,refusal", [
    (("+experiment=evaluate", "checkpoint=x"),  # another experiment
     "holds the results of +experiment=psf (metrics.json, mtf.png); +experiment=evaluate never writes into another "
     f"experiment's folder: {CHOOSE}"),
    (("+experiment=psf", "debug=smoke"),  # the same one, which does not resume: a rerun would overwrite it
     f"holds a finished +experiment=psf run (metrics.json, mtf.png); psf does not resume, and a rerun would "
     f"overwrite it: {CHOOSE}"),
], ids=["another_experiment", "same_without_resume"])
def test_an_earlier_runs_folder_is_refused_and_left_byte_identical(tmp_path, args, refusal):
    run_dir = tmp_path / "run"
    _earlier_run(run_dir, "psf")
    before = _tree(run_dir)
    proc = run_codesign(*args, f"hydra.run.dir={run_dir}")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1] == \
        f"codesign: configuration error: hydra.run.dir = '{run_dir}': {refusal}"
    assert _tree(run_dir) == before  # no .hydra/ rewritten, no log line appended


def test_the_same_training_experiment_may_continue_on_its_folder(tmp_path):
    for task in ("joint", "baseline"):
        run_dir = tmp_path / task
        _earlier_run(run_dir, task)
        (run_dir / ".codesign-run.json").write_text(json.dumps({"task": task, "state": "running", "pid": 1}))
        rundir.check_earlier_run(run_dir, task)  # a killed run: no error, resume is defined there (a finished one
        # runs again only with its own settings: tests/inputs/test_run_guard.py)
        with pytest.raises(ConfigError, match=rf"holds the results of \+experiment={task} "):
            rundir.check_earlier_run(run_dir, "mask_search")
    empty = tmp_path / "empty"
    empty.mkdir()
    rundir.check_earlier_run(empty, "psf")  # no run wrote there: any experiment may use it (a folder of the user's
    # files is refused: tests/inputs/test_run_folders.py)


def test_an_output_path_taken_by_a_folder_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "run"
    (run_dir / "metrics.json").mkdir(parents=True)
    line = config_error(monkeypatch, capsys, run_dir, "+experiment=psf", "debug=smoke")
    assert line == (f"codesign: configuration error: hydra.run.dir = '{run_dir}': metrics.json there is a folder, "
                    f"where the run writes its file metrics.json: move it away or choose another output folder "
                    f"with hydra.run.dir=PATH")
    assert [p.name for p in run_dir.iterdir()] == ["metrics.json"]


def test_every_experiment_declares_its_fixed_outputs():
    for name in experiments.EXPERIMENTS:
        outputs = experiments.protocol(name).outputs
        assert "metrics.json" in outputs, name


def test_a_refused_resume_cuts_the_log_back_to_the_earlier_run(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "run"
    _earlier_run(run_dir, "joint")
    before = _tree(run_dir)
    monkeypatch.setattr(rundir, "EARLIER", {})
    monkeypatch.setattr(rundir, "EARLIER_LOGS", {})
    rundir.remember(run_dir)
    with open(run_dir / "__main__.log", "a") as f:  # what Hydra's file handler writes for the refused run
        f.write("[codesign] refused run's line\n")
    (run_dir / "other.log").write_text("a log the refused run added\n")
    config_error(monkeypatch, capsys, run_dir, "+experiment=joint", "debug=smoke", "optics.focal_n=0")
    assert _tree(run_dir) == before
