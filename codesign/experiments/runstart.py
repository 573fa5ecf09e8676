"""The Hydra callbacks where every run starts (registered in conf/config.yaml under hydra.callbacks): a single
run's folder (rank 0 under torchrun) and a sweep's folder and job folders guarded before Hydra writes there
(rundir.guard, sweepdir.guard_sweep), each job of a sweep locked as it starts, and a launcher whose plugin is
missing named before Hydra's traceback."""
from __future__ import annotations

import sys
from pathlib import Path

from omegaconf import OmegaConf

from codesign.errors import ConfigError
from codesign.experiments.rundir import guard
from codesign.experiments.runlock import acquire_lock
from codesign.experiments.sweepdir import guard_sweep


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
        if ctx.is_main:  # under torchrun rank 0 alone writes, so it alone checks and records what was there
            folder = Path(str(OmegaConf.select(config, "hydra.run.dir")))
            try:
                _show_notes(guard(folder, OmegaConf.select(config, "task"), "hydra.run.dir", config))
            except ConfigError as err:
                _refuse(err)
        # ... before any other rank's Hydra creates the shared folder (which would look like an earlier run's)
        distributed.barrier(ctx)

    def on_multirun_start(self, config, **kwargs) -> None:  # runs before Hydra builds the launcher
        """Hydra callback before a sweep: the launcher checked, the sweep's folder and every job folder already
        in it guarded, before Hydra writes multirun.yaml or a job's .hydra/ and log."""
        _check_launcher(config)
        try:
            _show_notes(guard_sweep(config))
        except ConfigError as err:
            _refuse(err)

    def on_job_start(self, config, **kwargs) -> None:
        """Hydra callback as each job starts: a sweep's job folder locked (one made since the sweep started too)."""
        from hydra.types import RunMode

        if OmegaConf.select(config, "hydra.mode") != RunMode.MULTIRUN:
            return  # a single run's folder is locked in on_run_start
        folder = Path(str(OmegaConf.select(config, "hydra.runtime.output_dir")))
        try:
            _show_notes([n for n in [acquire_lock(folder, OmegaConf.select(config, "task"), "hydra.sweep.dir")] if n])
        except ConfigError as err:
            _refuse(err)


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
