"""What an experiment that runs a checkpoint (evaluate, restore) did with the physics, data and training keys typed
on its command line: the checkpoint's own values are used for most of them (the network was trained for its
physics and image geometry), so a typed value the run did not use is said in one log line naming each key, the
value typed and the value used (issue 59: ``optics.wavelength_m=5e-7`` ran under the checkpoint's wavelength
without a word about the key)."""
from __future__ import annotations

from omegaconf import OmegaConf

from codesign.config.runtime import to_container

# the blocks a checkpoint brings along: a typed key there may be replaced by the checkpoint's value
CHECKPOINT_BLOCKS = ("optics", "material", "mask", "sensor", "data", "model")
# the blocks of training, which a run of a trained checkpoint never reads
TRAINING_BLOCKS = ("trainer", "init", "codesign")
MISSING = object()


def _value(node, key: str):
    value = OmegaConf.select(node, key, default=MISSING) if node is not None else MISSING
    return to_container(value) if OmegaConf.is_config(value) else value


def _shown(value) -> str:
    if value is MISSING:
        return "(absent)"
    return "its block" if isinstance(value, (dict, list)) else repr(value)


def typed_values_unused(task: str, cfg, used, typed: frozenset[str]) -> list[str]:
    """'KEY = TYPED typed, VALUE used (the checkpoint's)' for each key typed on the command line (``typed``) under
    the checkpoint's blocks whose value in ``used`` (the configuration the run ran with) differs from this run's
    ``cfg``, and 'KEY = TYPED typed, not used (+experiment=TASK trains nothing)' for each training key."""
    out = []
    for key in sorted(typed):
        block = key.split(".")[0]
        here = _value(cfg, key)
        if block in TRAINING_BLOCKS:
            out.append(f"{key} = {_shown(here)} typed, not used (+experiment={task} trains nothing)")
        elif block in CHECKPOINT_BLOCKS:
            there = _value(used, key)
            if there != here:
                out.append(f"{key} = {_shown(here)} typed, {_shown(there)} used (the checkpoint's)")
    return out


def log_typed_values(log, task: str, cfg, used, typed: frozenset[str]) -> None:
    """One warning line listing typed_values_unused, when there is any."""
    unused = typed_values_unused(task, cfg, used, typed)
    if unused:
        log.warning("+experiment=%s runs the checkpoint with its own settings: %s", task, "; ".join(unused))
