"""The Hydra callbacks where every run starts (registered in conf/config.yaml under hydra.callbacks): a single
run's folder (rank 0 under torchrun) and a sweep's folder and job folders guarded before Hydra writes there
(rundir.guard, sweepdir.guard_sweep), each job of a sweep locked as it starts, the run's .hydra/ record written
without following a link (Hydra's own write, hydra.output_subdir, is off), and a launcher whose plugin is missing
named before Hydra's traceback."""
from __future__ import annotations

import copy
import errno
import sys
from pathlib import Path

from omegaconf import OmegaConf

from codesign.errors import ConfigError
from codesign.experiments.rundir import guard
from codesign.experiments.runlock import acquire_lock
from codesign.experiments.sweepdir import check_job_folder, guard_sweep
from codesign.io.logfile import write_text_nofollow

RECORD_DIR = ".hydra"  # where Hydra would write the run's config record (its default hydra.output_subdir)
# job folder -> job number of the jobs this process started in the current sweep (two jobs never share a folder)
SWEEP_JOBS: dict[Path, object] = {}


def _refuse(err: ConfigError) -> None:
    print(f"codesign: configuration error: {err}", file=sys.stderr)
    raise SystemExit(2) from None


def _show_notes(notes: list[str]) -> None:
    for note in notes:
        print(f"codesign: note: {note}", file=sys.stderr)


try:
    from hydra.experimental.callback import Callback
except ImportError:  # pragma: no cover - Hydra < 1.1
    Callback = object


class OutputDirCheck(Callback):
    def on_run_start(self, config, **kwargs) -> None:
        """Hydra callback before a single run: the run directory guarded (rank 0), then every rank waits."""
        from codesign.train import distributed

        ctx = distributed.current()
        refused = None
        if ctx.is_main:  # under torchrun rank 0 alone writes, so it alone checks and records what was there
            folder = Path(str(OmegaConf.select(config, "hydra.run.dir")))
            try:
                _show_notes(guard(folder, OmegaConf.select(config, "task"), "hydra.run.dir", config))
            except ConfigError as err:
                refused = err
        # every rank learns rank 0's verdict before its Hydra creates the shared folder (which would look like an
        # earlier run's) or its log there: a refused folder gets no rank's log (an audit found <job>.rank1.log in
        # the user's folder rank 0 had refused)
        if not distributed.broadcast_flag(refused is None, ctx):
            if refused is not None:
                _refuse(refused)
            raise SystemExit(2)  # rank 0 said why

    def on_multirun_start(self, config, **kwargs) -> None:  # runs before Hydra builds the launcher
        """Hydra callback before a sweep: the launcher checked, the sweep's folder and every job folder already
        in it guarded, before Hydra writes multirun.yaml or a job's .hydra/ and log."""
        _check_launcher(config)
        SWEEP_JOBS.clear()
        try:
            _show_notes(guard_sweep(config))
        except ConfigError as err:
            _refuse(err)

    def on_job_start(self, config, **kwargs) -> None:
        """Hydra callback as each job starts (after Hydra opened its log, before the task): a sweep's job folder
        locked (one made since the sweep started too; a single run's was locked in on_run_start), then the job's
        .hydra/ record written."""
        from hydra.types import RunMode

        folder = Path(str(OmegaConf.select(config, "hydra.runtime.output_dir")))
        multirun = OmegaConf.select(config, "hydra.mode") == RunMode.MULTIRUN
        key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
        try:
            if multirun:
                check_job_folder(config, folder, SWEEP_JOBS)
                _show_notes([n for n in [acquire_lock(folder, OmegaConf.select(config, "task"), key)] if n])
            write_hydra_record(config, folder, key)
        except ConfigError as err:
            _refuse(err)


def hydra_records(config) -> dict[str, str]:
    """The three files of the run's .hydra/ with the text Hydra's run_job writes there (hydra/core/utils.py): the
    job's config without its hydra node, Hydra's own config, the command line's overrides."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import open_dict, read_write

    task_cfg = copy.deepcopy(config)
    with read_write(task_cfg), open_dict(task_cfg):
        del task_cfg["hydra"]
    return {"config.yaml": OmegaConf.to_yaml(task_cfg), "hydra.yaml": OmegaConf.to_yaml(HydraConfig.instance().cfg),
            "overrides.yaml": OmegaConf.to_yaml(config.hydra.overrides.task)}


def write_hydra_record(config, folder: Path, key: str) -> None:
    """The run's .hydra/ record written into ``folder`` (rank 0 alone under torchrun), neither .hydra nor a file in
    it followed when it is a link (one swapped in after the guard): a ConfigError naming the link instead."""
    from codesign.train import distributed

    if not distributed.current().is_main:
        return
    for name, text in hydra_records(config).items():
        try:
            write_text_nofollow(folder / RECORD_DIR, name, text)
        except OSError as err:
            if err.errno not in (errno.ELOOP, errno.ENOTDIR, errno.EMLINK):
                raise
            raise ConfigError(key, str(folder), f"{RECORD_DIR}/{name} (or {RECORD_DIR}) became a symbolic link "
                              f"after the folder was checked; a run never writes through a link (it would change "
                              f"files outside its folder): remove the link, or choose another folder with "
                              f"{key}=PATH") from None


# launcher class -> the pip package that provides it (the optional extra: pip install '.[launchers]')
LAUNCHER_PACKAGES = {"hydra_plugins.hydra_joblib_launcher": "hydra-joblib-launcher",
                     "hydra_plugins.hydra_submitit_launcher": "hydra-submitit-launcher"}


def _installed(module: str) -> bool:
    import importlib.util

    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:  # the parent package (the hydra_plugins namespace) is missing too
        return False


def _check_launcher(config) -> None:
    """A launcher config whose plugin is not installed: one line naming the package, not Hydra's traceback."""
    target = str(OmegaConf.select(config, "hydra.launcher._target_") or "")
    module = target.rsplit(".", 1)[0]
    for prefix, package in LAUNCHER_PACKAGES.items():
        if module.startswith(prefix) and not _installed(prefix):
            choice = OmegaConf.select(config, "hydra.runtime.choices")
            name = choice.get("hydra/launcher") if choice is not None else None
            print(f"codesign: configuration error: hydra/launcher = {name or target}: needs the optional plugin "
                  f"{package}: pip install {package} (or pip install '.[launchers]' in the repository)",
                  file=sys.stderr)
            raise SystemExit(2)
