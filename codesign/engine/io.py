"""Atomic writers: every file appears whole or not at all (write to a temp file in the same folder, rename)."""
from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any, Callable

import numpy as np


def _atomic(path: Path, write: Callable[[str], None], suffix: str) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=suffix + ".tmp")
    os.close(fd)
    try:
        write(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file the permissions open() would
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


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
