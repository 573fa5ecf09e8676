"""Config-level helpers shared by every experiment: debug shrinking, typed keys, device and thread selection."""
from __future__ import annotations

import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf, open_dict

from codesign.errors import ConfigError, require_choice, require_number, unknown_keys


def apply_debug_overrides(cfg: DictConfig, explicit: frozenset[str] = frozenset()) -> list[str]:
    """Apply ``cfg.debug.overrides`` (dotted key -> value) after composition; returns the keys applied.

    Keys in ``explicit`` (given on the command line) are left alone: what a user types wins over the shrink.
    """
    dbg = cfg.get("debug")
    if not dbg or not dbg.get("overrides"):
        return []
    applied = []
    with open_dict(cfg):
        for key, value in dbg.overrides.items():
            if key in explicit:
                continue
            parent = key.rsplit(".", 1)[0] if "." in key else None
            if (parent is None and key in cfg) or (parent is not None and OmegaConf.select(cfg, parent) is not None):
                OmegaConf.update(cfg, key, value, merge=False)
                applied.append(key)
    return applied


def command_line_keys(overrides: list[str]) -> frozenset[str]:
    """Dotted keys set by Hydra command-line overrides ('+a.b=1', '++a=2', 'a.b=3' -> 'a.b', 'a', 'a.b')."""
    keys = set()
    for item in overrides:
        key = item.split("=", 1)[0].lstrip("+~")
        if key and not key.startswith("hydra."):
            keys.add(key)
    return frozenset(keys)


def explicit_keys() -> frozenset[str]:
    """Dotted keys typed on the command line of this Hydra run (empty outside Hydra)."""
    try:
        return command_line_keys(list(HydraConfig.get().overrides.task))
    except ValueError:
        return frozenset()


def to_container(node) -> dict:
    """A config node as plain Python containers, interpolations resolved ({} for None)."""
    return OmegaConf.to_container(node, resolve=True) if node is not None else {}


def resolve_device(name: str, local_rank: int | None = None) -> torch.device:
    """'auto' -> CUDA when available, else CPU; 'cpu', 'cuda', 'cuda:N' as given (validated).

    ``local_rank``: under torchrun each rank takes GPU cuda:<local_rank> (auto and cuda); cuda:N is refused there.
    """
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cpu":
        return torch.device("cpu")
    if isinstance(name, str) and (name == "cuda" or name.startswith("cuda:")):
        if not torch.cuda.is_available():
            raise ConfigError("device", name, "CUDA is not available on this machine; use device=cpu or auto")
        if local_rank is not None:
            if name != "cuda":
                raise ConfigError("device", name, "under torchrun each rank uses cuda:LOCAL_RANK: use device=auto "
                                  "or cuda (CUDA_VISIBLE_DEVICES picks the GPUs)")
            return torch.device(f"cuda:{local_rank}")
        try:
            dev = torch.device(name)
        except RuntimeError:
            raise ConfigError("device", name, "must be auto, cpu, cuda or cuda:N") from None
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError("device", name, f"this machine has {torch.cuda.device_count()} CUDA device(s)")
        return dev
    raise ConfigError("device", name, "must be auto, cpu, cuda or cuda:N")


def set_threads(threads) -> int:
    if threads is not None:
        torch.set_num_threads(require_number("threads", threads, lo=1, hi=1024, integer=True))
    return torch.get_num_threads()


def resolve_dtype(key: str, name: str) -> torch.dtype:
    return {"float32": torch.float32, "float64": torch.float64}[require_choice(key, name, ("float32", "float64"))]


def check_seed(cfg) -> int:
    """The root ``seed``: an integer (it seeds torch, numpy and the data draws; search.seed defaults to it)."""
    return require_number("seed", cfg.get("seed", 0), lo=0, hi=1e9, integer=True)


LOGGING_KEYS = ("tensorboard", "log_every")


def check_logging(cfg) -> None:
    """The ``logging`` block (conf/logging/default.yaml), whichever experiment runs."""
    node = cfg.get("logging")
    if node is None:
        return
    if not hasattr(node, "keys"):
        raise ConfigError("logging", node, "must be a mapping with tensorboard and log_every "
                          "(conf/logging/default.yaml)")
    unknown_keys("logging", node, LOGGING_KEYS)
    if not isinstance(node.get("tensorboard", True), bool):
        raise ConfigError("logging.tensorboard", node.get("tensorboard"), "must be true or false")
    require_number("logging.log_every", node.get("log_every", 10), lo=1, integer=True)
