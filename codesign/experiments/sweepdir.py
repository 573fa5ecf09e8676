"""A sweep's folder (``-m``, ``hydra.sweep.dir``) under the same guard as a single run's, before Hydra writes there.

Hydra writes multirun.yaml at the sweep's top and, per job, .hydra/ and the log into the job's folder before any
job code runs, so the judging happens here, in the callback before the sweep: the top folder is free when it is
empty or holds an earlier sweep of the same experiment (its multirun.yaml is that sweep's record), and every job
folder already in it is judged as a run folder of that experiment (rundir.guard: the user's files, another
experiment, a finished run, a link, a folder in use). Job folders made later are new; each job locks its own.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

from omegaconf import OmegaConf

from codesign.errors import ConfigError
from codesign.experiments import rundir
from codesign.experiments.runlinks import refuse_dangling, refuse_links
from codesign.experiments.runlock import LOCK, acquire_lock, release_lock
from codesign.io import files as io

KEY = "hydra.sweep.dir"
RECORD = "multirun.yaml"  # Hydra's record of a sweep, at its top
CHOOSE = f"choose another folder with {KEY}=PATH (or leave {KEY} unset: every sweep gets a new one)"


def recorded_task(top: Path) -> str | None:
    """The experiment of the codesign sweep recorded in ``top``/multirun.yaml ('unknown' when its experiment was
    swept or unreadable), or None when no Hydra sweep wrote that file (absent, or a file of the user's)."""
    try:
        record = OmegaConf.load(top / RECORD)
        if OmegaConf.select(record, "hydra.sweep.dir") is None:
            return None
    except Exception:  # noqa: BLE001 - not a Hydra record: the user's file
        return None
    task = record.get("task")
    return str(task) if task is not None else "unknown"


def _judge_top(top: Path, task) -> None:
    """ConfigError unless ``top`` holds nothing but job folders (judged one by one later) and, beside them, the
    multirun.yaml of an earlier sweep of ``task``: never the user's own files, never another experiment's sweep."""
    entries = sorted(p.name for p in top.iterdir() if p.name != LOCK)
    earlier = recorded_task(top) if RECORD in entries else None
    swept = f"+experiment={task}" if task is not None else "an experiment"
    theirs = [n for n in entries if not (top / n).is_dir() and not (n == RECORD and earlier is not None)]
    if theirs:
        raise ConfigError(KEY, str(top), f"holds files that no codesign sweep wrote ({rundir.shown_names(theirs)}); "
                          f"a sweep of {swept} writes only into an empty folder or its own earlier sweep's, never "
                          f"over files of yours: {CHOOSE}")
    if earlier is not None and (earlier != task or task is None):
        found = f"+experiment={earlier}" if earlier != "unknown" else "an unknown experiment"
        raise ConfigError(KEY, str(top), f"holds a sweep of {found} ({RECORD}); a sweep of {swept} never writes into "
                          f"another experiment's sweep folder: {CHOOSE}")


def _judge_job(job: Path, task) -> list[str]:
    """An existing job folder guarded as a run folder of ``task``; when the experiment is swept (no one ``task``)
    only an empty one is free: which experiment a job runs is not known before it starts."""
    held = sorted(p.name for p in job.iterdir())
    if task is None and held:
        raise ConfigError(KEY, str(job), f"holds an earlier job's files ({rundir.shown_names(held)}); a sweep "
                          f"over +experiment writes only into new job folders: {CHOOSE}")
    return rundir.guard(job, task, KEY)  # no config: a job's settings are composed later, per job


SUBDIR = "hydra.sweep.subdir"
# the interpolations that differ from one job of a sweep to the next: a subdir without one puts every job in one folder
PER_JOB = ("hydra.job.num", "hydra.job.override_dirname", "hydra.job.id")
INSIDE = f"a relative path inside {KEY} that names each job's own folder (the default: ${{hydra.job.num}})"


def _raw_subdir(config) -> str:
    """hydra.sweep.subdir as typed, its interpolations unresolved (hydra.job.num is not set before the jobs)."""
    sweep = OmegaConf.select(config, "hydra.sweep")
    return str(OmegaConf.to_container(sweep, resolve=False).get("subdir", "")) if sweep is not None else ""


def job_count(config) -> int | None:
    """How many jobs the sweep's overrides make (a product of each swept key's choices); None when it cannot be
    told before Hydra's sweeper runs (a glob, a sweeper plugin's own parameters)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    overrides = [str(o) for o in (OmegaConf.select(config, "hydra.overrides.task") or [])]
    params = OmegaConf.select(config, "hydra.sweeper.params") or {}
    overrides += [f"{k}={v}" for k, v in params.items()]
    count = 1
    try:
        for override in OverridesParser.create().parse_overrides(overrides):
            if override.is_sweep_override():
                count *= len(list(override.sweep_string_iterator()))
    except Exception:  # noqa: BLE001 - a sweep only Hydra's sweeper can expand: judged as each job starts
        return None
    return count


def check_subdir(config) -> None:
    """ConfigError before any job unless hydra.sweep.subdir stays inside the sweep's folder (a job writing
    outside it was never judged by the guard: it overwrote another sweep's finished job) and, for more than one
    job, differs from job to job (two jobs in one folder overwrite each other's results)."""
    raw = _raw_subdir(config)
    plain = os.path.normpath(re.sub(r"\$\{[^}]*\}", "x", raw)) if raw.strip() else "."
    if os.path.isabs(plain) or plain == "." or plain == ".." or plain.startswith(".." + os.sep):
        raise ConfigError(SUBDIR, raw, f"leaves the sweep's folder ({KEY}): a job never writes outside it (the "
                          f"guard judges only that folder): use {INSIDE}")
    count = job_count(config)
    if not any(name in raw for name in PER_JOB) and (count or 0) > 1:
        raise ConfigError(SUBDIR, raw, f"is the same for each of the sweep's {count} jobs: two jobs never share a "
                          f"folder (each would overwrite the other's results): use {INSIDE}")


def check_job_folder(config, folder: Path, seen: dict[Path, object]) -> None:
    """As a job starts: ConfigError unless its folder (``folder``, resolved) lies inside the sweep's folder and
    no earlier job of this sweep ran there (``seen``: job folder -> job number, this process's jobs)."""
    if OmegaConf.select(config, KEY) is None:
        return  # no sweep folder to stay inside (a launcher's own layout)
    top = Path(str(OmegaConf.select(config, KEY))).absolute()
    folder = Path(os.path.normpath(Path(folder).absolute()))
    if top not in folder.parents:
        raise ConfigError(SUBDIR, _raw_subdir(config), f"puts this job in {folder}, outside the sweep's folder "
                          f"{top}: a job never writes outside it: use {INSIDE}")
    num = OmegaConf.select(config, "hydra.job.num")
    if seen.get(folder, num) != num:
        raise ConfigError(SUBDIR, _raw_subdir(config), f"puts job {num} in {folder}, where job {seen[folder]} of "
                          f"this sweep ran: two jobs never share a folder (each would overwrite the other's "
                          f"results): use {INSIDE}")
    seen[folder] = num


def guard_sweep(config) -> list[str]:
    """Guard the sweep's top folder (locked for this process) and every job folder already in it; ConfigError
    after undoing what the locks changed. Returns the notes to show."""
    top = Path(str(OmegaConf.select(config, KEY))).absolute()
    task = OmegaConf.select(config, "task")
    check_subdir(config)
    refuse_dangling(top, KEY)
    io.check_writable_dir(top, KEY)
    refuse_links(top, KEY)  # before the lock, which opens a file in the folder
    rundir.remember(top)
    existed = rundir.existed_before(top)
    notes = [acquire_lock(top, task, KEY)]
    try:
        _judge_top(top, task)
        for job in sorted(p for p in top.iterdir() if p.is_dir()):
            notes += _judge_job(job, task)
            # judged free: unlocked again, each job locks its own folder as it starts (a launcher's job may run in
            # another process, which a lock held here would keep out)
            release_lock(job, rundir.EARLIER_OWN.get(job, {}).get(LOCK))
    except ConfigError:
        release_lock(top, rundir.EARLIER_OWN.get(top, {}).get(LOCK))
        if not existed:
            rundir.remove_if_empty(top)
        raise
    return [n for n in notes if n]
