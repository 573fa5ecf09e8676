"""One run per folder: a lock file (LOCK) in the run dir, flock()ed by the run that uses it, with its PID and
experiment, so that a second run started on the folder is refused naming the first. The kernel drops the flock of a
process that dies (SIGKILL too), so a LOCK left by a killed run is taken over, with a note."""
from __future__ import annotations

import atexit
import fcntl
import json
import os
import time
from pathlib import Path

from codesign.errors import ConfigError

LOCK = ".codesign.lock"  # {"pid", "task"} of the run using the folder, flock()ed while it runs; removed at its end
# absolute run dir -> (the open LOCK file this process holds, its PID): the kernel drops a dead process's flock
# (SIGKILL too); a forked child (a data loader's worker) inherits the entry but must not release the lock
HELD: dict[Path, tuple[int, int]] = {}


def _holder(path: Path) -> dict:
    """LOCK's {"pid", "task"}; ({} when unreadable)."""
    try:
        found = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return found if isinstance(found, dict) else {}


def _alive(pid) -> bool:
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: alive
        return True
    return True


def _who(holder: dict) -> str:
    task = f"+experiment={holder['task']} " if holder.get("task") else ""
    return f"a running {task}run (PID {holder['pid']})" if holder.get("pid") else "another running run"


def _open_locked(path: Path) -> int | None:
    """An fd of ``path`` with an exclusive flock, or None when another process holds it. Retried when the file
    was replaced meanwhile (a run ending removes it: an fd of the removed file locks nothing)."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)  # never a link's target
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return None
        try:
            if os.fstat(fd).st_ino == os.stat(path).st_ino:
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)


def acquire_lock(run_dir: Path, task: str | None, key: str = "hydra.run.dir") -> str | None:
    """Lock ``run_dir`` (created if needed) for this process until it ends: ConfigError naming the PID of the run
    that holds it. A LOCK left by a killed run (its process gone, so its flock too) is taken over: the note."""
    run_dir = Path(run_dir).absolute()
    if run_dir in HELD:
        return None  # this process holds it already (a second run in one process: the tests)
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / LOCK
    if os.path.lexists(path) and not path.is_file():  # a folder of the user's (a link is refused before the lock)
        raise ConfigError(key, str(run_dir), f"{LOCK} there is a folder or other non-file, where a run keeps its "
                          f"lock file: a run never replaces what is there: move it away, or choose another folder "
                          f"with {key}=PATH")
    try:
        fd = _open_locked(path)
    except OSError as err:  # a file system without flock (some network mounts): run, but say what is missing
        return f"{key} = '{run_dir}': cannot be locked ({type(err).__name__}: {err.strerror or err}): a second " \
               f"run started on this folder is not kept out"
    if fd is None:
        holder = _holder(path)
        for _ in range(20):  # the holder may have locked and not yet written its PID: wait for it a moment
            if _alive(holder.get("pid")):
                break
            time.sleep(0.05)
            holder = _holder(path)
        raise ConfigError(key, str(run_dir), f"is in use by {_who(holder)}: two runs never share a folder (each "
                          f"would overwrite the other's results): wait for it to end, or choose another folder with "
                          f"{key}=PATH (or leave {key} unset: every run gets a new one)")
    stale = os.read(fd, 4096)
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps({"pid": os.getpid(), "task": task}).encode() + b"\n", 0)
    if not HELD:
        atexit.register(_release_all)
    HELD[run_dir] = (fd, os.getpid())
    return _stale_note(run_dir, stale, key) if stale.strip() else None


def _stale_note(run_dir: Path, stale: bytes, key: str) -> str:
    try:
        holder = json.loads(stale)
    except ValueError:
        holder = {}
    holder = holder if isinstance(holder, dict) else {}
    who = f"PID {holder['pid']}" if holder.get("pid") else "an unknown process"
    task = f" (+experiment={holder['task']})" if holder.get("task") else ""
    return f"{key} = '{run_dir}': the lock of {who}{task}, which no longer runs, is taken over: that run was killed"


def release_lock(run_dir: Path, earlier: bytes | None = None) -> None:
    """Unlock ``run_dir`` if this process holds it: LOCK removed, or ``earlier`` (its content before this run)
    written back."""
    run_dir = Path(run_dir).absolute()
    if HELD.get(run_dir, (None, None))[1] != os.getpid():
        return  # not locked, or locked by the parent of this forked process
    fd, _ = HELD.pop(run_dir)
    path = run_dir / LOCK
    try:
        if path.is_file() and os.stat(path).st_ino == os.fstat(fd).st_ino:
            if earlier is None:
                path.unlink()
            else:
                os.ftruncate(fd, 0)
                os.pwrite(fd, earlier, 0)
    finally:
        os.close(fd)  # the flock goes with it


def _release_all() -> None:
    for run_dir in list(HELD):
        release_lock(run_dir)
