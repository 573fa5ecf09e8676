"""Issue 59's audit of run and sweep folders: a sweep's jobs stay inside hydra.sweep.dir, each in its own folder; a
dangling link as the run folder and a folder where the lock file goes are refused in one line."""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from codesign.errors import ConfigError
from codesign.experiments import rundir, runlock, sweepdir
from codesign.experiments.rundir import STATE
from tests.cli import run_codesign
from tests.inputs._run import fresh_run_folder_state  # noqa: F401 (autouse: the guard's records, fresh per test)

INSIDE = "a relative path inside hydra.sweep.dir that names each job's own folder (the default: ${hydra.job.num})"


def _sweep_config(top: Path, subdir: str, *overrides: str, num: int = 0, job_dir: Path | None = None):
    """The part of Hydra's config that the sweep callbacks read."""
    return OmegaConf.create({"task": "psf", "hydra": {
        "sweep": {"dir": str(top), "subdir": subdir}, "overrides": {"task": ["+experiment=psf", *overrides]},
        "job": {"num": num}, "runtime": {"output_dir": str(job_dir or top / str(num))}}}, flags={"allow_objects": True})


@pytest.mark.parametrize("subdir", ["../../outside/esc_${hydra.job.num}", "/abs/x_${hydra.job.num}", "../sw_ok/0",
                                    "a/../../${hydra.job.num}", ""])
def test_a_sweep_subdir_leaving_the_sweep_folder_is_refused(tmp_path, subdir):
    config = _sweep_config(tmp_path / "S", subdir, "seed=0,1")
    with pytest.raises(ConfigError) as info:
        sweepdir.check_subdir(config)
    assert str(info.value) == (f"hydra.sweep.subdir = {subdir!r}: leaves the sweep's folder (hydra.sweep.dir): a job "
                               f"never writes outside it (the guard judges only that folder): use {INSIDE}")


@pytest.mark.parametrize("subdir", ["${hydra.job.num}", "runs/${hydra.job.override_dirname}", "a/b_${hydra.job.id}"])
def test_a_sweep_subdir_inside_the_sweep_folder_and_per_job_is_free(tmp_path, subdir):
    sweepdir.check_subdir(_sweep_config(tmp_path / "S", subdir, "seed=0,1", "data.image_size=32,64"))


def test_a_sweep_whose_jobs_would_share_a_folder_is_refused_before_any_job(tmp_path):
    config = _sweep_config(tmp_path / "S", "same", "seed=0,1", "data.image_size=32,64")
    with pytest.raises(ConfigError) as info:
        sweepdir.check_subdir(config)
    assert str(info.value) == (f"hydra.sweep.subdir = 'same': is the same for each of the sweep's 4 jobs: two jobs "
                               f"never share a folder (each would overwrite the other's results): use {INSIDE}")
    sweepdir.check_subdir(_sweep_config(tmp_path / "S", "same", "seed=0"))  # one job: its own folder


def test_a_second_job_in_an_earlier_jobs_folder_or_outside_the_sweep_is_refused_as_it_starts(tmp_path):
    """A sweep whose job count only Hydra's sweeper knows: each job judged as it starts."""
    seen = {}
    sweepdir.check_job_folder(_sweep_config(tmp_path / "S", "${x}", job_dir=tmp_path / "S" / "j"), tmp_path / "S" / "j",
                              seen)
    with pytest.raises(ConfigError, match=r"puts job 1 in .*/S/j, where job 0 of this sweep ran: two jobs never"):
        sweepdir.check_job_folder(_sweep_config(tmp_path / "S", "${x}", num=1), tmp_path / "S" / "j", seen)
    with pytest.raises(ConfigError, match=r"puts this job in .*/other, outside the sweep's folder .*/S: a job never"):
        sweepdir.check_job_folder(_sweep_config(tmp_path / "S", "${x}", num=2), tmp_path / "S" / ".." / "other", seen)


def test_a_sweep_into_another_sweeps_finished_job_is_refused_and_the_job_kept(tmp_path):
    """The audit's case: hydra.sweep.subdir=../sw_ok/0 overwrote a finished psf job's metrics.json (the guard
    judged only the folders inside hydra.sweep.dir)."""
    job = tmp_path / "sw_ok" / "0"
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "config.yaml").write_text("task: psf\nseed: 0\n")
    (job / "metrics.json").write_text('{"finished": 1}')
    (job / STATE).write_text(json.dumps({"task": "psf", "state": "finished", "pid": 1}))
    before = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in job.rglob("*") if p.is_file()}
    proc = run_codesign("-m", "+experiment=psf", "debug=smoke", "seed=0,1", f"hydra.sweep.dir={tmp_path / 'S'}",
                        "hydra.sweep.subdir=../sw_ok/${hydra.job.num}")
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == (
        "codesign: configuration error: hydra.sweep.subdir = '../sw_ok/${hydra.job.num}': leaves the sweep's folder "
        f"(hydra.sweep.dir): a job never writes outside it (the guard judges only that folder): use {INSIDE}")
    assert {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in job.rglob("*") if p.is_file()} == before
    assert not (tmp_path / "S").exists() and sorted(p.name for p in (tmp_path / "sw_ok").iterdir()) == ["0"]


@pytest.mark.parametrize("under", [False, True])
def test_a_dangling_link_as_the_run_folder_is_refused(tmp_path, under):
    link = tmp_path / "X"
    link.symlink_to(tmp_path / "gone")
    folder = link / "run" if under else link
    with pytest.raises(ConfigError) as info:
        rundir.guard(folder, "psf", "hydra.run.dir")
    where = f"lies under {link}, which is" if under else "is"
    assert str(info.value) == (f"hydra.run.dir = '{folder}': {where} a symbolic link to {tmp_path / 'gone'}, which "
                               f"does not exist; a run never follows a link to make its folder: create the target "
                               f"folder first, or choose another folder with hydra.run.dir=PATH")
    assert os.path.islink(link) and not (tmp_path / "gone").exists()


def test_a_folder_where_the_lock_file_goes_is_refused_untouched(tmp_path):
    (tmp_path / "run" / runlock.LOCK).mkdir(parents=True)
    (tmp_path / "run" / runlock.LOCK / "mine.txt").write_text("user's")
    with pytest.raises(ConfigError) as info:
        rundir.guard(tmp_path / "run", "psf", "hydra.run.dir")
    assert str(info.value) == (f"hydra.run.dir = '{tmp_path / 'run'}': {runlock.LOCK} there is a folder or other "
                               f"non-file, where a run keeps its lock file: a run never replaces what is there: move "
                               f"it away, or choose another folder with hydra.run.dir=PATH")
    assert (tmp_path / "run" / runlock.LOCK / "mine.txt").read_text() == "user's" and not runlock.HELD
