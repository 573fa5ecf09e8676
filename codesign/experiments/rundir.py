"""The run directory before Hydra touches it: writable, and what an earlier run left there kept safe.

Hydra creates the run dir and writes .hydra/ and its log before our task function starts, so an unwritable
hydra.run.dir would otherwise end in Hydra's own traceback. ``OutputDirCheck`` (registered in conf/config.yaml
under hydra.callbacks) runs first: it refuses an unwritable folder, and a folder that holds another experiment's
results (or a finished run of an experiment that does not resume: a rerun would overwrite it), before anything
is written there. It remembers whether the run dir already existed, what its .hydra/ held and how long its logs
were, so that a run stopped later by a configuration error leaves an earlier run's folder as it found it.
"""
from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

from omegaconf import OmegaConf

from codesign.errors import ConfigError
from codesign.io import files as io

# absolute run dir that existed before this run -> {file name in its .hydra/: bytes}, or None without a .hydra/
EARLIER: dict[Path, dict[str, bytes] | None] = {}
# absolute run dir that existed before this run -> {log file name: its size in bytes then}
EARLIER_LOGS: dict[Path, dict[str, int]] = {}


def remember(run_dir: Path) -> None:
    """Record that ``run_dir`` exists already, with the contents of its .hydra/ (small YAML files) and the sizes
    of its logs."""
    run_dir = Path(run_dir).absolute()
    if run_dir.is_dir():
        hydra_dir = run_dir / ".hydra"
        EARLIER[run_dir] = {f.name: f.read_bytes() for f in sorted(hydra_dir.glob("*.yaml")) if f.is_file()} \
            if hydra_dir.is_dir() else None
        EARLIER_LOGS[run_dir] = {f.name: f.stat().st_size for f in run_dir.glob("*.log") if f.is_file()}


def existed_before(run_dir: Path) -> bool:
    return Path(run_dir).absolute() in EARLIER


def restore_earlier(run_dir: Path) -> None:
    """Put ``run_dir``'s .hydra/ back as the earlier run left it (Hydra rewrote it for the refused run)."""
    _restore_logs(Path(run_dir))
    files = EARLIER.get(Path(run_dir).absolute())
    hydra_dir = Path(run_dir) / ".hydra"
    if files is None:  # the folder had no .hydra/: remove the one the refused run added
        shutil.rmtree(hydra_dir, ignore_errors=True)
        return
    for name, data in files.items():
        io.atomic_write_bytes(hydra_dir / name, lambda f, d=data: f.write(d))


def _restore_logs(run_dir: Path) -> None:
    """Cut the earlier run's logs back to their length before this run appended to them; drop logs it added."""
    sizes = EARLIER_LOGS.get(run_dir.absolute(), {})
    for f in run_dir.glob("*.log"):
        if f.name in sizes:
            os.truncate(f, sizes[f.name])  # Hydra's handler appends (O_APPEND): a later line lands at the end
        else:
            f.unlink(missing_ok=True)


def earlier_results(run_dir: Path) -> list[str]:
    """The names of what an earlier run left in ``run_dir`` besides Hydra's .hydra/ and logs."""
    names = sorted(p.name for p in Path(run_dir).iterdir() if p.name != ".hydra" and p.suffix != ".log")
    return sorted(names, key=lambda n: n != "metrics.json")  # the file that says "results" first


def earlier_experiment(run_dir: Path) -> str | None:
    """The experiment recorded in ``run_dir``/.hydra/config.yaml, or None without one."""
    recorded = Path(run_dir) / ".hydra" / "config.yaml"
    if not recorded.is_file():
        return None
    try:
        task = OmegaConf.load(recorded).get("task")
    except Exception:  # noqa: BLE001 - an unreadable record is treated as an unknown experiment's
        return "unknown"
    return str(task) if task is not None else None


def check_earlier_run(run_dir: Path, task: str | None, key: str = "hydra.run.dir") -> None:
    """ConfigError when ``run_dir`` holds another experiment's results, or a finished run of ``task`` that
    cannot be resumed (a rerun would overwrite its metrics.json). The same experiment continues where it
    defines resume (a killed training run started again on its folder)."""
    from codesign.experiments import EXPERIMENTS, protocol

    run_dir = Path(run_dir).absolute()
    if task not in EXPERIMENTS or not run_dir.is_dir():
        return  # no experiment: run_experiment names the choices
    earlier, results = earlier_experiment(run_dir), earlier_results(run_dir)
    if earlier is None and not (run_dir / "metrics.json").is_file():
        return  # an empty folder, or a folder of the user's that no run wrote
    shown = ", ".join(results[:4]) + (f" and {len(results) - 4} more" if len(results) > 4 else "")
    choose = f"choose another folder with {key}=PATH (or leave {key} unset: every run gets a new one)"
    if earlier != task:
        found = f"+experiment={earlier}" if earlier not in (None, "unknown") else "an unknown experiment"
        raise ConfigError(key, str(run_dir), f"holds the results of {found} ({shown or '.hydra/'}); "
                          f"+experiment={task} never writes into another experiment's folder: {choose}")
    finished = (run_dir / "metrics.json").is_file()  # written last: a killed run's leftovers may be replaced
    if finished and not protocol(task).resumes:
        raise ConfigError(key, str(run_dir), f"holds a finished +experiment={task} run ({shown}); {task} does not "
                          f"resume, and a rerun would overwrite it: {choose}")


def _check(config, key: str) -> None:
    folder = OmegaConf.select(config, key)
    try:
        io.check_writable_dir(Path(str(folder)), key)
        if key == "hydra.run.dir":
            check_earlier_run(Path(str(folder)), OmegaConf.select(config, "task"), key)
    except ConfigError as err:
        print(f"codesign: configuration error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    remember(Path(str(folder)))


try:
    from hydra.experimental.callback import Callback
except ImportError:  # pragma: no cover - Hydra < 1.1
    Callback = object


class OutputDirCheck(Callback):
    def on_run_start(self, config, **kwargs) -> None:
        from codesign.train import distributed

        ctx = distributed.current()
        if ctx.is_main:  # under torchrun rank 0 alone writes, so it alone checks and records what was there
            _check(config, "hydra.run.dir")
        # ... before any other rank's Hydra creates the shared folder (which would look like an earlier run's)
        distributed.barrier(ctx)

    def on_multirun_start(self, config, **kwargs) -> None:  # runs before Hydra builds the launcher
        _check_launcher(config)
        _check(config, "hydra.sweep.dir")


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
