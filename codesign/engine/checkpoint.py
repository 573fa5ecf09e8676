"""Checkpoints: one dict (models, optimizers, schedulers, step, RNG states, resolved config), written atomically."""
from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import torch

from codesign.engine import io
from codesign.errors import ConfigError

CHECKPOINT_NAME = "checkpoint.pt"


def save_checkpoint(path: Path, state: dict) -> Path:
    """torch.save to a temp file in the same folder, then rename: a crash never leaves half a checkpoint."""
    return io.atomic_write_bytes(Path(path), lambda f: torch.save(state, f))


def load_checkpoint(path: str | Path, key: str = "checkpoint") -> dict:
    """Load a checkpoint dict on the CPU; a missing or foreign file is a ConfigError naming ``key``."""
    p = Path(str(path)).expanduser()
    if not p.is_file():
        raise ConfigError(key, str(path), "no such checkpoint file")
    try:
        # weights_only: a checkpoint holds tensors and plain Python values only, so a file from elsewhere can
        # never run code while it is read
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any unpickling failure means "not our checkpoint"
        first = str(err).strip().splitlines()[0][:200] if str(err).strip() else ""
        raise ConfigError(key, str(path), f"cannot be read as a codesign checkpoint (tensors and plain values "
                          f"only): {type(err).__name__}: {first}") from None
    if not isinstance(state, dict) or "model" not in state or "config" not in state:
        raise ConfigError(key, str(path), "is not a codesign checkpoint (no 'model' / 'config' entries)")
    return state


def rng_state() -> dict:
    """Global RNG states as tensors and plain values (loadable with weights_only=True)."""
    name, keys, pos, has_gauss, cached = np.random.get_state()
    out = {"torch": torch.get_rng_state(), "numpy": [name, torch.from_numpy(keys.astype(np.int64)), int(pos),
                                                     int(has_gauss), float(cached)],
           "python": random.getstate()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        out["cuda"] = torch.cuda.get_rng_state_all()
    return out


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
    random.setstate(tuple(tuple(x) if isinstance(x, list) else x for x in state["python"]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
