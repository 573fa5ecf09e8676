"""Atomic writers: every file appears whole or not at all (write to a temp file in the same folder, rename)."""
from __future__ import annotations

import json
import math
import os
import re
import tempfile
from pathlib import Path
from typing import Any, Callable

import numpy as np

from codesign.errors import ConfigError, OutputWriteError


# The temp files of _atomic (mkstemp: ".<stem>." + 8 random characters + "<suffix>.tmp") and of check_writable_dir:
# only a killed process leaves one behind (every other failure removes it), and the next run in the folder removes it
TEMP_NAME = re.compile(r"^\..+\.[a-z0-9_]{8}(\.[^.]+)?\.tmp$|^\.codesign-write-test\.[a-z0-9_]{8}$")


def is_temp(name: str) -> bool:
    """Whether ``name`` is a temp file of the atomic writers (or of the writability probe)."""
    return TEMP_NAME.match(name) is not None


def leftover_temps(folder: Path, prune: Callable[[Path], bool] = lambda d: False) -> list[Path]:
    """The temp files a killed run left in ``folder`` and its subfolders (symlinks not followed, nor the subfolders
    ``prune`` names: another run's folder inside this one), sorted."""
    found = []
    for top, dirs, names in os.walk(folder):
        dirs[:] = [d for d in dirs if not prune(Path(top) / d)]
        found += [Path(top) / n for n in names if is_temp(n)]
    return sorted(found)


def remove_temps(folder: Path, prune: Callable[[Path], bool] = lambda d: False) -> list[Path]:
    """Remove the temp files a killed run left in ``folder`` (call it only while no other run writes there: the
    run-directory lock); returns them."""
    found = leftover_temps(folder, prune)
    for path in found:
        path.unlink(missing_ok=True)
    return found


def _atomic(path: Path, write: Callable[[str], None], suffix: str) -> Path:
    """Run ``write(tmp)`` on a temp file next to ``path``, flush it to disk, then rename it over ``path``.

    Any failure (a full disk, a read-only folder, an exception inside ``write``) removes the temp file and leaves
    the previous ``path`` untouched; an OSError is re-raised as OutputWriteError naming the file.
    """
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=suffix + ".tmp")
        os.close(fd)
        write(tmp)
        _fsync(tmp)  # the data reaches the disk before the rename: a crash never leaves an empty file behind
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file the permissions open() would
        os.replace(tmp, path)
    except BaseException as err:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(err, OSError) and not isinstance(err, OutputWriteError):
            raise OutputWriteError(f"cannot write {path} ({type(err).__name__}: {err.strerror or err}); "
                                   f"an earlier {path.name}, if any, is unchanged") from err
        raise
    return path


def _fsync(name: str) -> None:
    fd = os.open(name, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def check_writable_dir(folder: Path, key: str = "hydra.run.dir") -> None:
    """ConfigError naming ``key`` unless files can be created in ``folder`` (or, when it does not exist yet, in
    its nearest existing ancestor). Tried for real (a temp file, removed at once): permission bits say nothing
    for root or on read-only mounts. Called before any work, so that an hour of training never ends in a
    failed write."""
    folder = Path(folder).absolute()
    probe = folder
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    if not probe.is_dir():
        raise ConfigError(key, str(folder), f"cannot be created: {probe} is a file, not a folder; choose another "
                          f"output folder with {key}=PATH")
    try:
        fd, tmp = tempfile.mkstemp(dir=probe, prefix=".codesign-write-test.")
        os.close(fd)
        os.unlink(tmp)
    except OSError as err:
        raise ConfigError(key, str(folder), f"is not writable ({type(err).__name__}: {err.strerror or err} in "
                          f"{probe}): choose a writable output folder with {key}=PATH") from None


def check_output_files(folder: Path, names: tuple[str, ...], key: str = "hydra.run.dir") -> None:
    """ConfigError naming ``key`` before any work when one of the files ``names`` in ``folder`` could not be
    replaced: a folder or other non-file stands at its path (the rename at the end of the run would fail)."""
    for name in names:
        path = Path(folder) / name
        if path.exists() and not path.is_file():
            kind = "a folder" if path.is_dir() else "something other than a file"
            raise ConfigError(key, str(Path(folder).absolute()), f"{name} there is {kind}, where the run writes its "
                              f"file {name}: move it away or choose another output folder with {key}=PATH")


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.floating, np.integer)):
        v = v.item()
    if hasattr(v, "item") and getattr(v, "ndim", 1) == 0:
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None  # JSON has no NaN/Inf; None marks a value that could not be computed
    return v


def write_json(path: Path, data: dict[str, Any]) -> Path:
    """Write a dict (nested dicts and lists allowed; NaN/Inf -> null) as pretty JSON, atomically."""
    clean = {k: _jsonable(v) for k, v in data.items()}

    def w(tmp: str) -> None:
        with open(tmp, "w") as f:
            json.dump(clean, f, indent=2, sort_keys=True)
            f.write("\n")

    return _atomic(path, w, ".json")


def save_npy(path: Path, array: Any) -> Path:
    """Write an array (or tensor, moved to the CPU) as .npy, atomically; returns ``path``."""
    arr = np.asarray(array.detach().cpu().numpy() if hasattr(array, "detach") else array)

    def w(tmp: str) -> None:
        with open(tmp, "wb") as f:
            np.save(f, arr)

    return _atomic(path, w, ".npy")


def atomic_write_bytes(path: Path, write) -> Path:
    """Write binary content through ``write(file_object)``, atomically."""
    def w(tmp: str) -> None:
        with open(tmp, "wb") as f:
            write(f)

    return _atomic(path, w, Path(path).suffix)


def save_figure(path: Path, fig) -> Path:
    """Save a matplotlib figure as PNG atomically and close it."""
    import matplotlib.pyplot as plt

    try:
        return _atomic(path, lambda tmp: fig.savefig(tmp, format="png", dpi=120, bbox_inches="tight"), ".png")
    finally:
        plt.close(fig)
