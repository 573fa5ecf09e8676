"""Checkpoints: one dict (models, optimizers, schedulers, step, RNG states, resolved config), written atomically."""
from __future__ import annotations

import pickle
import random
from pathlib import Path

import numpy as np
import torch

from codesign.errors import ConfigError, require_number, special_file
from codesign.io import files as io
from codesign.train.spec import MAX_STEPS

CHECKPOINT_NAME = "checkpoint.pt"


def save_checkpoint(path: Path, state: dict) -> Path:
    """torch.save to a temp file in the same folder, then rename: a crash never leaves half a checkpoint."""
    return io.atomic_write_bytes(Path(path), lambda f: torch.save(state, f))


def _unreadable(p: Path, err: Exception) -> str:
    """Why torch.load failed on ``p``, in the user's terms (torch's own text speaks of zip readers and pickles)."""
    with open(p, "rb") as f:
        head = f.read(4)
    text = str(err).strip()
    refused = isinstance(err, pickle.UnpicklingError) and "weights only" in text.lower()
    if not head:
        return "is empty (0 bytes): not a checkpoint (an interrupted copy?)"
    if refused and (head.startswith(b"PK") or head[:1] == b"\x80"):  # a whole archive / legacy pickle
        return ("holds Python objects other than tensors and plain values: refused, since reading them could run "
                "code (codesign checkpoints hold tensors and plain values only)")
    if head.startswith(b"PK"):  # torch's zip format whose archive cannot be read: cut short or damaged
        first = text.splitlines()[0].split(". ")[0][:160] if text else type(err).__name__
        return f"is truncated or corrupt ({first}); copy it again, or use an earlier checkpoint"
    return "is not a torch checkpoint file (it is neither a torch archive nor a pickle)"


# checkpoints shipped in the package, found by name (checkpoint=pretrained, init.checkpoint=pretrained); their model
# cards beside them (codesign/models/pretrained/README.md)
PRETRAINED_DIR = Path(__file__).resolve().parents[1] / "models" / "pretrained"
PRETRAINED = {"pretrained": "wiener_naf_pool.pt"}


def checkpoint_path(path: str | Path, key: str = "checkpoint") -> Path:
    """The file of ``path``: a shipped checkpoint's name (PRETRAINED) or a path."""
    name = str(path)
    if name in PRETRAINED:
        p = PRETRAINED_DIR / PRETRAINED[name]
        if not p.is_file():
            raise ConfigError(key, name, f"names the shipped restorer {p}, which this installation lacks (reinstall "
                              "codesign, or give a checkpoint path)")
        return p
    return Path(name).expanduser()


def load_checkpoint(path: str | Path, key: str = "checkpoint") -> dict:
    """Load a checkpoint dict on the CPU (``path``: a file, or a shipped checkpoint's name, e.g. 'pretrained'); a
    missing, truncated or foreign file is a ConfigError naming ``key``."""
    p = checkpoint_path(path, key)
    if p.is_dir():
        inside = p / CHECKPOINT_NAME
        hint = f": give the file, e.g. {key}={inside}" if inside.is_file() else ""
        raise ConfigError(key, str(path), f"is a folder, not a checkpoint file{hint}")
    if not p.is_file():
        kind = special_file(p)  # a device or a pipe exists: "no such file" would send the user looking for it
        raise ConfigError(key, str(path), f"is {kind}, not a regular file: give a checkpoint file (checkpoint.pt "
                          f"of a training run) or pretrained" if kind else "no such checkpoint file")
    try:
        # weights_only: a checkpoint holds tensors and plain Python values only, so a file from elsewhere can
        # never run code while it is read
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any unpickling failure means "not our checkpoint"
        raise ConfigError(key, str(path), _unreadable(p, err)) from None
    if not isinstance(state, dict) or "model" not in state or "config" not in state:
        raise ConfigError(key, str(path), "is not a codesign checkpoint (no 'model' / 'config' entries)")
    bad = first_nonfinite(state)
    if bad is not None:
        # refused whole, before anything is built from it: a NaN weight (a diverged run, a damaged copy) turns every
        # result into NaN (evaluate "nan dB", restore all-zero images, a warm start trained to the end for nothing)
        where, tensor = bad
        where = where if len(where) <= 200 else where[:200] + "..."  # a foreign file's keys may be of any length
        raise ConfigError(key, str(path), f"is not usable: tensor {where} holds {nonfinite_summary(tensor)} (the "
                          f"first non-finite tensor in the file; results computed from it would be NaN): use an "
                          f"earlier checkpoint of the run")
    return state


def nonfinite_summary(t: torch.Tensor) -> str | None:
    """``"3 NaN and 1 +inf of 432 values"`` for a tensor with non-finite values, None when every value is finite
    (integer tensors always are)."""
    if not (t.is_floating_point() or t.is_complex()):
        return None
    x = torch.view_as_real(t) if t.is_complex() else t
    if bool(torch.isfinite(x).all()):
        return None
    counts = {"NaN": int(torch.isnan(x).sum()), "+inf": int((x == float("inf")).sum()),
              "-inf": int((x == float("-inf")).sum())}
    return " and ".join(f"{n} {kind}" for kind, n in counts.items() if n) + f" of {x.numel()} values"


def first_nonfinite(state) -> tuple[str, torch.Tensor] | None:
    """(where, tensor) of the first tensor in ``state`` (dicts, lists and tuples, in stored order) holding NaN or
    inf, ``where`` as it is indexed (``model['g1.head.0.0.weight']``, ``opt_g['state'][0]['exp_avg']``); None when
    every tensor is finite. Walked with a stack, not recursion: a deeply nested file cannot overflow Python's."""
    stack = [("", state)]
    while stack:
        where, value = stack.pop()
        if torch.is_tensor(value):
            if nonfinite_summary(value) is not None:
                return where, value
            continue
        if isinstance(value, dict):
            items = [(f"{where}[{k!r}]" if where else str(k), v) for k, v in value.items()]
        elif isinstance(value, (list, tuple)):
            items = [(f"{where}[{i}]", v) for i, v in enumerate(value)]
        else:
            continue
        stack.extend(reversed(items))  # popped first to last: the first bad tensor in the file's order
    return None


def stored_config_error(key: str, path, err: ConfigError) -> ConfigError:
    """``err`` raised by a value of a checkpoint's stored configuration, named as coming from that file (not as if
    it had been typed on this command line)."""
    return ConfigError(key, str(path), f"its stored configuration is not valid in this version of codesign: {err}")


# What a checkpoint written by the trainer holds, and the config blocks a model and its simulator are built from.
TRAINED_ENTRIES = ("model", "step", "config")
CONFIG_BLOCKS = ("model", "optics", "mask", "sensor", "data")
RESUME_ENTRIES = ("opt_g", "opt_d", "sched_g", "sched_d", "rng")


def check_trained(state: dict, path, key: str, resume: bool = False) -> None:
    """A checkpoint to evaluate, restore with or (``resume``) continue: every entry the trainer writes present,
    its configuration holding every block the model and simulator are built from; ConfigError naming the file."""
    need = TRAINED_ENTRIES + (RESUME_ENTRIES if resume else ())
    missing = [k for k in need if k not in state]
    cfg = state.get("config")
    if not missing and not isinstance(cfg, dict):
        missing = ["config (a mapping)"]
    if not missing:
        missing = [f"config.{k}" for k in CONFIG_BLOCKS if not isinstance(cfg.get(k), dict)]
    if missing:
        raise ConfigError(key, str(path), f"is not a complete codesign training checkpoint: no {', '.join(missing)} "
                          f"entry")
    check_step(state, path, key)


def check_step(state: dict, path, key: str) -> None:
    """A checkpoint's ``step``: a count of training steps (an integer >= 0), refused at load otherwise. -5, 4.7 or
    True were reported as the steps trained (evaluate's metrics.json, a warm start's record) and a text ended in a
    ValueError after the work."""
    step = state.get("step")
    try:
        require_number("step", step, lo=0, hi=MAX_STEPS, integer=True)
    except ConfigError as err:
        shown = repr(step) if len(repr(step)) <= 80 else repr(step)[:76] + " ..."
        raise ConfigError(key, str(path), f"its entry step = {shown}: {err.allowed} (the training steps it "
                          f"holds)") from None


def state_mismatch(module: torch.nn.Module, state: dict) -> str | None:
    """How a state dict differs from ``module``'s (missing, unexpected, other shapes), or None when it fits."""
    if not isinstance(state, dict):
        return f"a {type(state).__name__} where a state dict belongs"
    own = module.state_dict()
    missing = [k for k in own if k not in state]
    extra = [k for k in state if k not in own]
    shapes = [k for k in own if k in state and hasattr(state[k], "shape")
              and tuple(state[k].shape) != tuple(own[k].shape)]
    # a floating tensor stored as integers (int64 weights) would be copied in rounded, without a word; the model's
    # own integer buffers (a BatchNorm's num_batches_tracked) stay integers
    kinds = [k for k in own if k in state and torch.is_tensor(state[k]) and k not in shapes
             and own[k].is_floating_point() and not (state[k].is_floating_point() or state[k].is_complex())]
    parts = []
    if kinds:
        k = kinds[0]
        parts.append(f"tensor {k!r} holds {str(state[k].dtype).replace('torch.', '')} values where the model has "
                     f"{str(own[k].dtype).replace('torch.', '')} (allowed: floating point)"
                     + (f" and {len(kinds) - 1} more" if len(kinds) > 1 else ""))
    if missing:
        parts.append(f"{len(missing)} tensor(s) missing (e.g. {missing[0]!r})")
    if extra:
        parts.append(f"{len(extra)} unexpected (e.g. {extra[0]!r})")
    if shapes:
        k = shapes[0]
        parts.append(f"{len(shapes)} of another shape (e.g. {k!r}: {list(state[k].shape)} in the file, "
                     f"{list(own[k].shape)} here)")
    return "; ".join(parts) or None


def load_error(key: str, path, what: str, detail) -> ConfigError:
    """A ConfigError naming the checkpoint for a state that does not fit what it is loaded into (another model
    variant or size, another mask, another codesign version). ``detail``: a state_mismatch text or the error."""
    if isinstance(detail, BaseException):
        lines = [ln.strip() for ln in str(detail).strip().splitlines() if ln.strip()]
        detail = f"{type(detail).__name__}: " + (lines[-1][:200] if lines else "")
    return ConfigError(key, str(path), f"{what}: {detail}; was it written by another configuration or version of "
                       f"codesign?")


def load_module_state(module: torch.nn.Module, state, key: str, path, what: str) -> None:
    """``module.load_state_dict(state)``, any misfit a ConfigError naming ``key`` and the file."""
    problem = state_mismatch(module, state)
    if problem:
        raise load_error(key, path, what, problem)
    try:
        module.load_state_dict(state)
    except (RuntimeError, KeyError, TypeError, ValueError) as err:
        raise load_error(key, path, what, err) from None


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
    """Restore the torch, numpy, Python (and CUDA, when present) random states of ``rng_state()``."""
    torch.set_rng_state(state["torch"])
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
    random.setstate(tuple(tuple(x) if isinstance(x, list) else x for x in state["python"]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
