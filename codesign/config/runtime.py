"""Config-level helpers shared by every experiment: debug shrinking, typed keys, device and thread selection."""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any, Mapping

import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf, open_dict

from codesign.config.store import register, spec_node
from codesign.errors import ConfigError, require_choice, require_number
from codesign.spec_base import SpecMixin


def apply_debug_overrides(cfg: DictConfig, explicit: frozenset[str] = frozenset(),
                          reads: tuple[str, ...] | None = None, own: Mapping[str, Any] | None = None) -> list[str]:
    """Apply ``cfg.debug.overrides`` (dotted key -> value) after composition, and with debug=smoke the experiment's
    ``own`` shrink of its own keys (its protocol's ``smoke``); returns the keys applied.

    Keys in ``explicit`` (given on the command line) are left alone: what a user types wins over the shrink.
    ``reads``: the root keys the experiment reads (None: all); a key under any other root is not applied, so the
    log of what was applied names only what shrinks this experiment.
    """
    dbg = cfg.get("debug")
    if not dbg:
        return []
    overrides = dict(dbg.get("overrides") or {})
    if dbg.get("name") == "smoke":
        overrides.update(own or {})
    applied = []
    with open_dict(cfg):
        for key, value in overrides.items():
            if key in explicit or (reads is not None and key.split(".", 1)[0] not in reads):
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


def mask_typed(typed: frozenset[str]) -> bool:
    """Whether a command line (``typed``: explicit_keys()) gives the mask: evaluate and restore then image through
    it, not through the checkpoint's (a restorer trained for many masks, data.masks, restores through any)."""
    return any(k == "mask" or k.startswith("mask.") for k in typed)


def with_typed_mask(ckpt_cfg: DictConfig, cfg: DictConfig, typed: frozenset[str]) -> DictConfig:
    """A checkpoint's configuration with this run's mask block when the command line gives one (mask_typed), in
    place; as it was otherwise."""
    if mask_typed(typed):
        ckpt_cfg.mask = OmegaConf.create(OmegaConf.to_container(cfg.mask, resolve=True))
    return ckpt_cfg


def to_container(node) -> dict:
    """A config node as plain Python containers, interpolations resolved ({} for None)."""
    return OmegaConf.to_container(node, resolve=True) if node is not None else {}


# Keys that were renamed or moved: typed on the command line they stop the run with the new key's name, before
# Hydra composes (Hydra would only say that the old key is not in the config).
RENAMED_KEYS: dict[str, str] = {
    "lsr_smooth_p": "metrics.lsr_p", "mtf_band": "metrics.mtf_band",
    "codesign.lsr_p": "metrics.lsr_p", "codesign.mtf_band": "metrics.mtf_band",
    "search.lsr_p": "metrics.lsr_p", "search.mtf_band": "metrics.mtf_band",
    "search.r_bounds": "mask.r_bounds (the search explores the mask family's own box)",
    "search.theta_bounds": "nothing: theta_n is periodic and the search explores [0, 2 pi)",
    "mask.basis": "the family's own config group: mask=pixel or mask=zernike (mask=freeform keeps mask.basis)",
    "search.check_tolerance": "metrics.recheck_tolerance (the re-check of every experiment)",
    "simulate.alpha_l": "simulate.laser_strengths (as evaluate.laser_strengths)",
}


def renamed_key_error(argv: list[str]) -> str | None:
    """The message for a renamed key (RENAMED_KEYS) or for trainer=paper alone among the command-line arguments
    ``argv``, else None."""
    keys = command_line_keys([a for a in argv if "=" in a])
    for key in sorted(keys):
        if key in RENAMED_KEYS and not (key == "mask.basis" and any(a == "mask=freeform" for a in argv)):
            return f"{key} was renamed: use {RENAMED_KEYS[key]}"
    if "trainer=paper" in argv and not any(a.startswith("preset=") for a in argv):
        return ("trainer=paper sets the paper's schedule only; the paper's network widths and image sizes are "
                "preset=paper: add preset=paper (or name the preset you want, e.g. preset=cpu)")
    return None


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
    """Set torch's intra-op threads to ``threads`` (checked: 1..1024; None leaves torch's choice); returns the number
    in use."""
    if threads is not None:
        torch.set_num_threads(require_number("threads", threads, lo=1, hi=1024, integer=True))
    return torch.get_num_threads()


def set_deterministic(mode: bool | str, device: torch.device) -> bool:
    """Switch torch's deterministic kernels on or off for this process (``mode``: RunSpec.deterministic); returns
    whether they are on.

    Why: on the CPU the backward of an advanced-indexing gather (``values[index]``, e.g. the half-ring mask's
    octant sums and radial profiles spread over the pupil) accumulates with ``index_put_(accumulate=True)``,
    which for more than ~32k indices runs on several threads with atomic float adds: the mask's gradient then
    differs in its last bits from call to call, and a joint run parts from itself after ~100 steps. torch's
    deterministic mode sorts the indices instead (as fast here: docs/codesign.md). On CUDA it would also need
    CUBLAS_WORKSPACE_CONFIG and slower convolution algorithms, so ``auto`` leaves it off there; ``true`` sets both.
    Ops without a deterministic kernel warn (warn_only) rather than stop the run."""
    on = device.type == "cpu" if mode == "auto" else bool(mode)
    if on and device.type == "cuda":
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.backends.cudnn.benchmark = False
    torch.use_deterministic_algorithms(on, warn_only=True)
    return on


def resolve_dtype(key: str, name: str) -> torch.dtype:
    """The torch dtype of a precision setting ``name`` (float32 or float64); ConfigError naming ``key`` otherwise."""
    return {"float32": torch.float32, "float64": torch.float64}[require_choice(key, name, ("float32", "float64"))]


# Root keys some experiments share, each with its one default, composed at the root by the experiments' YAMLs
# (``- /root_keys/precision: default``). The groups are not named after the keys: a group named ``precision``
# would turn ``precision=float64`` on the command line into a choice of group option.
register("root_keys/precision", "default", {"precision": "float32"}, package="_global_")  # float32 | float64
register("root_keys/checkpoint", "required", {"checkpoint": None}, package="_global_")  # a checkpoint path, required
register("root_keys/input", "required", {"input": None}, package="_global_")  # a capture file or folder, required


@dataclass(frozen=True)
class RunSpec(SpecMixin):
    """The root keys of every run: seed (torch, numpy and the data draws; search.seed defaults to it); device:
    auto (CUDA when present, else CPU) | cpu | cuda | cuda:N; threads: torch intra-op threads (null: torch's
    default); deterministic: auto (on for CPU runs, off on CUDA) | true | false, torch's deterministic kernels
    (see set_deterministic)."""

    seed: int = 0
    device: str = "auto"
    threads: int | None = None
    deterministic: bool | str = "auto"
    prefix: str = field(default="", compare=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "seed", require_number("seed", self.seed, lo=0, hi=1e9, integer=True))
        if self.threads is not None:
            object.__setattr__(self, "threads", require_number("threads", self.threads, lo=1, hi=1024, integer=True))
        if self.deterministic not in (True, False, "auto"):
            raise ConfigError("deterministic", self.deterministic, "must be auto, true or false")


register("run", "default", {**spec_node(RunSpec)}, package="_global_")


def run_spec(cfg) -> RunSpec:
    """The validated root keys of a composed config (RunSpec's defaults for keys it lacks)."""
    return RunSpec(**{k: cfg.get(k) for k in ("seed", "device", "threads", "deterministic") if cfg.get(k) is not None})


def check_seed(cfg) -> int:
    """The root ``seed`` (RunSpec)."""
    return run_spec(cfg).seed


@dataclass(frozen=True)
class LoggingSpec(SpecMixin):
    """Run outputs: every experiment writes metrics.json; tensorboard: TensorBoard events under the run dir;
    log_every: steps (or evaluations) between progress lines and logged losses."""

    tensorboard: bool = True
    log_every: int = 10
    prefix: str = field(default="logging", compare=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.tensorboard, bool):
            raise ConfigError("logging.tensorboard", self.tensorboard, "must be true or false")
        object.__setattr__(self, "log_every", require_number("logging.log_every", self.log_every, lo=1,
                                                             integer=True))


def logging_spec(cfg) -> LoggingSpec:
    """The validated ``logging`` block of a composed config (defaults when it has none), whichever experiment."""
    node = cfg.get("logging")
    if node is None:
        return LoggingSpec()
    if not hasattr(node, "keys"):
        raise ConfigError("logging", node, "must be a mapping with tensorboard and log_every")
    return LoggingSpec.from_config(dict(node))


def tensorboard_enabled(cfg) -> bool:
    """``logging.tensorboard`` of a composed config (the LoggingSpec default when the block is absent)."""
    return logging_spec(cfg).tensorboard


check_logging = logging_spec  # validates; the runner calls it before any work

register("logging", "default", spec_node(LoggingSpec))
