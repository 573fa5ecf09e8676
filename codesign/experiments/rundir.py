"""The run directory before Hydra touches it: writable, free, locked, and what an earlier run left there kept safe.

Hydra creates the run dir and writes .hydra/ and its log before our task function starts, so an unwritable
hydra.run.dir would otherwise end in Hydra's own traceback. ``guard`` (called by the Hydra callbacks of
runstart.py for a single run and every job of a sweep, and by codesign.run) runs first, on the folder as the user
left it: it refuses an unwritable folder, a folder another run is using (LOCK), a symbolic link inside the folder,
a folder of the user's own files, and a folder that holds another experiment's results or a finished run (a rerun
would overwrite it; a resuming experiment's finished run only runs again with its very settings), before anything
is written there. It remembers whether the run dir already existed, what its .hydra/ held and how long its logs were,
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
from pathlib import Path

from omegaconf import OmegaConf

from codesign.config.compare import described, differences, flat_keys
from codesign.errors import ConfigError
from codesign.io import files as io
from codesign.experiments.runlinks import refuse_dangling, refuse_links
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
    else:  # new now, whatever it was at an earlier run of this process (the Python API runs many)
        for record in (EARLIER, EARLIER_LOGS, EARLIER_OWN):
            record.pop(run_dir, None)


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


def shown_names(names: list[str]) -> str:
    """The first four of ``names`` joined by commas, then "and N more": the file list of a refusal message."""
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
    """The experiment recorded in ``run_dir``/.hydra/config.yaml (or, for a run without Hydra's record such as the
    Python API's, in its STATE), or None without one."""
    recorded = Path(run_dir) / ".hydra" / "config.yaml"
    if not recorded.is_file():
        state = read_state(run_dir)
        return str(state["task"]) if state and state.get("task") else None
    try:
        task = OmegaConf.load(recorded).get("task")
    except Exception:  # noqa: BLE001 - an unreadable record is treated as an unknown experiment's
        return "unknown"
    return str(task) if task is not None else None


def check_earlier_run(run_dir: Path, task: str | None, key: str = "hydra.run.dir", config=None) -> str | None:
    """ConfigError when ``run_dir`` holds a symbolic link, files of the user's, another experiment's results, or a
    finished run of ``task`` (a rerun would overwrite it) other than a resumable one made with exactly the settings
    of ``config`` (this run's composed config; None: unknown, so refused). The same experiment continues where it
    defines resume (a killed training run started again on its folder), and runs again in its own unfinished run's
    folder: then the note to show. An empty folder is free."""
    from codesign.experiments import EXPERIMENTS, protocol

    run_dir = Path(run_dir).absolute()
    if task not in EXPERIMENTS or not run_dir.is_dir():
        return None  # no experiment: run_experiment names the choices
    refuse_links(run_dir, key)
    earlier, results = earlier_experiment(run_dir), earlier_results(run_dir)
    choose = f"choose another folder with {key}=PATH (or leave {key} unset: every run gets a new one)"
    if earlier is None and not (run_dir / "metrics.json").is_file():
        theirs = sorted(p.name for p in run_dir.iterdir() if p.name != LOCK)
        if theirs:  # no run recorded its config here: the user's own files, never ours to replace
            raise ConfigError(key, str(run_dir), f"holds files that no codesign run wrote ({shown_names(theirs)}); "
                              f"+experiment={task} writes only into an empty folder or its own earlier run's, never "
                              f"over files of yours: {choose}")
        return None
    if earlier != task:
        found = f"+experiment={earlier}" if earlier not in (None, "unknown") else "an unknown experiment"
        raise ConfigError(key, str(run_dir), f"holds the results of {found} "
                          f"({shown_names(results) or '.hydra/'}); "
                          f"+experiment={task} never writes into another experiment's folder: {choose}")
    why = unfinished(run_dir)
    if why is not None:
        if protocol(task).resumes:
            return None  # the experiment itself continues from its checkpoint
        return f"{key} = '{run_dir}': holds an unfinished +experiment={task} run ({why}); this run replaces its results"
    if not protocol(task).resumes:
        raise ConfigError(key, str(run_dir), f"holds a finished +experiment={task} run "
                          f"({shown_names(results)}); {task} does not resume, and a rerun would overwrite it: {choose}")
    return _same_settings(run_dir, task, results, config, key, choose)


# keys that change how a run is executed, never what it computes
UNCOMPARED = ("hydra", "threads")


def changed_settings(run_dir: Path, config) -> list[tuple[str, object, object]] | None:
    """(key, value recorded in ``run_dir``'s .hydra/config.yaml, value in ``config``) for every setting that
    differs; None when either is missing or unreadable (the run's settings cannot be told)."""
    recorded = Path(run_dir) / ".hydra" / "config.yaml"
    if config is None or not recorded.is_file():
        return None
    try:
        old = flat_keys(OmegaConf.to_container(OmegaConf.load(recorded), resolve=False))
    except Exception:  # noqa: BLE001 - an unreadable record tells no settings
        return None
    return differences(old, flat_keys(OmegaConf.to_container(config, resolve=False)), UNCOMPARED)


def _same_settings(run_dir: Path, task: str, results: list[str], config, key: str, choose: str) -> str:
    """A finished run of a resuming experiment runs again in place only with the very settings it was made with
    (its results come out the same: the checkpoint and finished stages are reused); else a ConfigError."""
    differ = changed_settings(run_dir, config)
    finished = f"holds a finished +experiment={task} run ({shown_names(results)})"
    never = f"a finished run is never rewritten in place (to evaluate it otherwise: +experiment=evaluate " \
            f"checkpoint={run_dir / 'checkpoint.pt'}): {choose}"
    if differ is None:
        why = "a sweep's job is composed only as it starts" if config is None else \
            "no readable .hydra/config.yaml there"
        raise ConfigError(key, str(run_dir), f"{finished} whose settings cannot be compared with this run's ({why}); "
                          f"{never}")
    if differ:
        more = f" and {len(differ) - 3} more" if len(differ) > 3 else ""
        raise ConfigError(key, str(run_dir), f"{finished} that was trained with different "
                          f"{', '.join(k for k, _, _ in differ[:3])}{more}: {described(differ[:3], 3, quoted=False)}; "
                          f"{never}")
    return f"{key} = '{run_dir}': holds a finished +experiment={task} run made with these same settings: it is " \
           f"run again in place, its checkpoint and finished parts reused"


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


def remove_if_empty(folder: Path) -> None:
    """Remove ``folder`` if it is empty (made for a refused run's lock); leave it if another run wrote there since."""
    try:
        folder.rmdir()
    except OSError:  # not empty: another run's now
        pass


def guard(folder: Path, task, key: str = "hydra.run.dir", config=None) -> list[str]:
    """The one run-folder guard of every way a run starts (the command, each job of a sweep, codesign.run,
    torchrun's rank 0): ``folder`` writable, what it holds recorded (a refused run puts it back), locked for this
    process, then judged (check_earlier_run: links, the user's files, another experiment, a finished run). A
    refusal is a ConfigError raised after the lock's changes are undone: the folder as it was, byte for byte.
    Returns the notes to show."""
    folder = Path(folder)
    refuse_dangling(folder, key)
    io.check_writable_dir(folder, key)
    refuse_links(folder, key)  # before the lock, which opens a file in the folder
    remember(folder)
    existed = existed_before(folder)
    notes = [acquire_lock(folder, task, key)]  # first: the folder is judged with no other run writing there
    try:
        notes.append(check_earlier_run(folder, task, key, config))
    except ConfigError:
        release_lock(folder, EARLIER_OWN.get(folder.absolute(), {}).get(LOCK))
        if not existed:
            remove_if_empty(folder)  # made for the lock
        raise
    return [n for n in notes if n]
