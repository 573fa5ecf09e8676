"""The run directory before Hydra touches it: writable, free, locked, and what an earlier run left there kept safe.

Hydra creates the run dir and writes .hydra/ and its log before our task function starts, so an unwritable
hydra.run.dir would otherwise end in Hydra's own traceback. ``OutputDirCheck`` (registered in conf/config.yaml
under hydra.callbacks) runs first, on the folder as the user left it: it refuses an unwritable folder, a folder
another run is using (LOCK), a folder of the user's own files, and a folder that holds another experiment's
results or a finished run of an experiment that does not resume (a rerun would overwrite it), before anything is
written there. It remembers whether the run dir already existed, what its .hydra/ held and how long its logs were,
so that a run stopped later by a configuration error leaves an earlier run's folder as it found it.

Which earlier run is finished: STATE, written "running" when the work starts and "finished" after the experiment
returned, its last write; a run killed before (SIGKILL, a crash, an interrupt) is unfinished, and the same
experiment may run again in its folder, replacing its results (the temp files of its killed writes removed first).
A folder of an earlier version (no STATE): finished when it holds metrics.json and no temp file (metrics.json was
that version's last write, but for mask_search's figures: a temp file left beside it marks the kill).
"""
from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

from omegaconf import OmegaConf

from codesign.errors import ConfigError
from codesign.io import files as io
from codesign.experiments.runlock import LOCK, acquire_lock, release_lock

STATE = ".codesign-run.json"  # {"task", "state": "running" | "finished", "pid"}: "finished" is a run's last write

# absolute run dir that existed before this run -> {file name in its .hydra/: bytes}, or None without a .hydra/
EARLIER: dict[Path, dict[str, bytes] | None] = {}
# absolute run dir that existed before this run -> {log file name: its size in bytes then}
EARLIER_LOGS: dict[Path, dict[str, int]] = {}
# absolute run dir that existed before this run -> {LOCK or STATE: its bytes then, or None without one}
EARLIER_OWN: dict[Path, dict[str, bytes | None]] = {}


def remember(run_dir: Path) -> None:
    """Record that ``run_dir`` exists already, with the contents of its .hydra/ (small YAML files), the sizes
    of its logs and its LOCK and STATE."""
    run_dir = Path(run_dir).absolute()
    if run_dir.is_dir():
        hydra_dir = run_dir / ".hydra"
        EARLIER[run_dir] = {f.name: f.read_bytes() for f in sorted(hydra_dir.glob("*.yaml")) if f.is_file()} \
            if hydra_dir.is_dir() else None
        EARLIER_LOGS[run_dir] = {f.name: f.stat().st_size for f in run_dir.glob("*.log") if f.is_file()}
        EARLIER_OWN[run_dir] = {n: _bytes(run_dir / n) for n in (LOCK, STATE)}


def _bytes(path: Path) -> bytes | None:
    try:
        return path.read_bytes()
    except OSError:
        return None


def _put_back(path: Path, data: bytes | None) -> None:
    """``path`` as it was: ``data`` written back, or the file removed when there was none."""
    if data is None:
        path.unlink(missing_ok=True)
    else:
        io.atomic_write_bytes(path, lambda f: f.write(data))


def existed_before(run_dir: Path) -> bool:
    """Whether ``run_dir`` existed before this run started (a folder being resumed)."""
    return Path(run_dir).absolute() in EARLIER


def restore_earlier(run_dir: Path) -> None:
    """Put ``run_dir``'s .hydra/ back as the earlier run left it (Hydra rewrote it for the refused run), and its
    logs, STATE and LOCK."""
    _restore_logs(Path(run_dir))
    own = EARLIER_OWN.get(Path(run_dir).absolute())
    if own is not None:
        _put_back(Path(run_dir) / STATE, own.get(STATE))
        release_lock(run_dir, own.get(LOCK))
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


def is_own(name: str) -> bool:
    """A file of the run dir's bookkeeping (LOCK, STATE) or a temp file of a killed write: no result."""
    return name in (LOCK, STATE) or io.is_temp(name)


def earlier_results(run_dir: Path) -> list[str]:
    """The names of what an earlier run left in ``run_dir`` besides Hydra's .hydra/ and logs and our own files."""
    names = sorted(p.name for p in Path(run_dir).iterdir()
                   if p.name != ".hydra" and p.suffix != ".log" and not is_own(p.name))
    return sorted(names, key=lambda n: n != "metrics.json")  # the file that says "results" first


def _shown(names: list[str]) -> str:
    return ", ".join(names[:4]) + (f" and {len(names) - 4} more" if len(names) > 4 else "")


def read_state(run_dir: Path) -> dict | None:
    """STATE of ``run_dir``: None without one (a folder of an earlier version, or no run started work there)."""
    data = _bytes(Path(run_dir) / STATE)
    if data is None:
        return None
    try:
        state = json.loads(data)
    except ValueError:
        state = None
    return state if isinstance(state, dict) else {"state": "unreadable"}


def _another_run(folder: Path) -> bool:
    """A subfolder that is another run's folder (evaluate's run inside a joint run's): its temps are its own."""
    return (folder / ".hydra").is_dir() or (folder / LOCK).exists()


def unfinished(run_dir: Path) -> str | None:
    """Why the run in ``run_dir`` did not finish, or None when it did (see the module's docstring)."""
    state = read_state(run_dir)
    if state is not None:  # anything but "running" counts as finished: never replace what might be results
        return "killed or stopped before its end" if state.get("state") == "running" else None
    if not (Path(run_dir) / "metrics.json").is_file():
        return "it never wrote metrics.json"
    temps = io.leftover_temps(run_dir, _another_run)
    return f"killed during a write: {len(temps)} temp file(s) left" if temps else None


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


def check_earlier_run(run_dir: Path, task: str | None, key: str = "hydra.run.dir") -> str | None:
    """ConfigError when ``run_dir`` holds files of the user's, another experiment's results, or a finished run of
    ``task`` that cannot be resumed (a rerun would overwrite it). The same experiment continues where it defines
    resume (a killed training run started again on its folder), and runs again in its own unfinished run's
    folder: then the note to show. An empty folder is free."""
    from codesign.experiments import EXPERIMENTS, protocol

    run_dir = Path(run_dir).absolute()
    if task not in EXPERIMENTS or not run_dir.is_dir():
        return None  # no experiment: run_experiment names the choices
    earlier, results = earlier_experiment(run_dir), earlier_results(run_dir)
    choose = f"choose another folder with {key}=PATH (or leave {key} unset: every run gets a new one)"
    if earlier is None and not (run_dir / "metrics.json").is_file():
        theirs = sorted(p.name for p in run_dir.iterdir() if p.name != LOCK)
        if theirs:  # no run recorded its config here: the user's own files, never ours to replace
            raise ConfigError(key, str(run_dir), f"holds files that no codesign run wrote ({_shown(theirs)}); "
                              f"+experiment={task} writes only into an empty folder or its own earlier run's, never "
                              f"over files of yours: {choose}")
        return None
    if earlier != task:
        found = f"+experiment={earlier}" if earlier not in (None, "unknown") else "an unknown experiment"
        raise ConfigError(key, str(run_dir), f"holds the results of {found} ({_shown(results) or '.hydra/'}); "
                          f"+experiment={task} never writes into another experiment's folder: {choose}")
    if protocol(task).resumes:
        return None  # the experiment itself continues from its checkpoint
    why = unfinished(run_dir)
    if why is None:
        raise ConfigError(key, str(run_dir), f"holds a finished +experiment={task} run ({_shown(results)}); {task} "
                          f"does not resume, and a rerun would overwrite it: {choose}")
    return f"{key} = '{run_dir}': holds an unfinished +experiment={task} run ({why}); this run replaces its results"


# ---- the run's own marks: temps of a killed run removed, "finished" written last ------------------------------
def start_work(run_dir: Path, task: str) -> list[Path]:
    """Before the experiment's work: remove the temp files a killed run left, mark the run unfinished (a run
    killed from here on is never counted as finished). Returns the temp files removed."""
    removed = io.remove_temps(run_dir, _another_run) if Path(run_dir).is_dir() else []
    _write_state(run_dir, task, "running")
    return removed


def finish_work(run_dir: Path, task: str) -> None:
    """After the experiment returned, everything written: the completion mark, the run's last write."""
    _write_state(run_dir, task, "finished")


def _write_state(run_dir: Path, task: str, state: str) -> None:
    io.write_json(Path(run_dir) / STATE, {"task": task, "state": state, "pid": os.getpid()})


def _refuse(err: ConfigError) -> None:
    print(f"codesign: configuration error: {err}", file=sys.stderr)
    raise SystemExit(2) from None


def _check(config, key: str) -> None:
    folder = Path(str(OmegaConf.select(config, key)))
    try:
        io.check_writable_dir(folder, key)
    except ConfigError as err:
        _refuse(err)
    remember(folder)
    if key == "hydra.run.dir":
        _check_run_dir(folder, OmegaConf.select(config, "task"), key)


def _remove_if_empty(folder: Path) -> None:
    try:
        folder.rmdir()
    except OSError:  # not empty: another run's now
        pass


def _check_run_dir(folder: Path, task, key: str) -> None:
    """Lock the run dir first (the folder is judged with no other run writing there), then judge what it holds;
    a refusal puts back what the lock changed: the folder as it was, byte for byte."""
    existed = existed_before(folder)
    try:
        notes = [acquire_lock(folder, task, key)]
    except ConfigError as err:
        _refuse(err)
    try:
        notes.append(check_earlier_run(folder, task, key))
    except ConfigError as err:
        release_lock(folder, EARLIER_OWN.get(folder.absolute(), {}).get(LOCK))
        if not existed:
            _remove_if_empty(folder)  # made for the lock
        _refuse(err)
    for note in filter(None, notes):
        print(f"codesign: note: {note}", file=sys.stderr)


try:
    from hydra.experimental.callback import Callback
except ImportError:  # pragma: no cover - Hydra < 1.1
    Callback = object


class OutputDirCheck(Callback):
    def on_run_start(self, config, **kwargs) -> None:
        """Hydra callback before a single run: the run directory checked and what it held recorded (rank 0), then
        every rank waits."""
        from codesign.train import distributed

        ctx = distributed.current()
        if ctx.is_main:  # under torchrun rank 0 alone writes, so it alone checks and records what was there
            _check(config, "hydra.run.dir")
        # ... before any other rank's Hydra creates the shared folder (which would look like an earlier run's)
        distributed.barrier(ctx)

    def on_multirun_start(self, config, **kwargs) -> None:  # runs before Hydra builds the launcher
        """Hydra callback before a sweep: the launcher and the sweep directory checked."""
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
