"""Loading a checkpoint's weights and state: resuming a trainer, a warm start's weights, the EMA averages, a
co-design checkpoint's learned mask, and a trained restorer for evaluation. What the run's configuration must share
with the checkpoint is checked first, at the boundary (codesign/experiments/resume.py)."""
from __future__ import annotations

import logging

import torch
from omegaconf import OmegaConf

from codesign.errors import ConfigError
from codesign.train.checkpoint import check_trained, load_checkpoint, load_error, load_module_state, state_mismatch
from codesign.train.model_setup import build_model
from codesign.train.optim import EMA

log = logging.getLogger("codesign.train")


def check_resume_steps(done, steps: int, path) -> None:
    """A resume continues a training up to trainer.steps: one asked to stop before the checkpoint's step would
    report the checkpoint's steps as this run's; a ConfigError naming both."""
    if isinstance(done, int) and not isinstance(done, bool) and done > steps:
        raise ConfigError("trainer.steps", steps, f"is fewer than the {done} steps already trained in the checkpoint "
                          f"it resumes ({path}): a resume trains on up to trainer.steps, never back: set "
                          f"trainer.steps={done} or more, or start a new run directory")


def resume_trainer(trainer, state: dict, path) -> None:
    """Continue ``trainer`` from a checkpoint's ``state`` (its configuration already checked against the run's):
    the weights must fit the model, the step must not exceed trainer.steps, and the optimizers must take theirs."""
    problem = state_mismatch(trainer.model, state["model"])
    if problem:
        raise load_error("trainer.resume", path, "cannot be resumed: its weights do not fit this run's model", problem)
    check_resume_steps(state.get("step"), trainer.spec.steps, path)
    try:
        trainer.load_state_dict(state)
    except (RuntimeError, KeyError, ValueError, TypeError, IndexError) as err:
        raise load_error("trainer.resume", path, "cannot be resumed: its state does not fit this run's model "
                         "and optimizers", err) from None
    log.info("resumed from %s at step %d (written by %d process(es), resumed by %d)", path, trainer.step,
             int(state.get("world_size", 1)), trainer.dist.world)


def warm_start(model, state: dict, key: str, path) -> dict:
    """Start ``model`` from a checkpoint's weights (its configuration already checked against the run's): weights
    only, the generators' EMA averages where the checkpoint has them. Returns what the run records: the path and the
    checkpoint's step and mask family."""
    facts = model.summary()
    what = (f"its weights do not fit this run's model (model.kind={model.kind}, variant={facts['variant']}, "
            f"size={facts['size']})")
    load_module_state(model, state["model"], key, path, what)
    if state.get("ema"):  # the generators the checkpoint restores with (and was evaluated with): its averages
        load_ema_weights(model.generators(), state, key, path, what)
    mask = OmegaConf.select(OmegaConf.create(state["config"]), "mask.kind")
    log.info("network weights from %s (step %d, trained on mask %s)", path, int(state["step"]), mask)
    return {"init_checkpoint": str(path), "init_steps": int(state["step"]), "init_mask_kind": mask}


def load_ema_weights(generators: list, state: dict, key: str, path, what: str) -> None:
    """The checkpoint's EMA generator states into ``generators`` (one per generator, in order)."""
    states = state["ema"]
    if not isinstance(states, list) or len(states) != len(generators):
        n = len(states) if isinstance(states, list) else "no list of"
        raise load_error(key, path, what, f"its EMA holds {n} generator state(s), the model has {len(generators)} "
                         "generators")
    for g, st in zip(generators, states):
        load_module_state(g, st, key, path, what + " (EMA weights)")


def apply_checkpoint_mask(mask, state: dict, path="checkpoint", key: str = "checkpoint") -> None:
    """A co-design checkpoint carries its learned mask: load it over the configured one."""
    if state.get("mask") is not None:
        load_module_state(mask, state["mask"], key, path, f"its learned mask does not fit the {type(mask).__name__} "
                          "of its configuration")


def load_trained(path, device: torch.device, key: str = "checkpoint"):
    """(model, generators for restoration, checkpoint config, state) from a checkpoint written by the trainer;
    every way the file can be wrong (incomplete, a configuration this version refuses, weights that do not fit
    the model its configuration describes) is a ConfigError naming ``key`` and the file."""
    state = load_checkpoint(path, key)
    check_trained(state, path, key)
    ckpt_cfg = OmegaConf.create(state["config"])
    try:
        model = build_model(ckpt_cfg)
    except ConfigError as err:
        raise ConfigError(key, str(path), f"its stored configuration is not valid in this version of codesign: "
                          f"{err}") from None
    facts = model.summary()  # the restorer interface's, so any plug-in network is named (not SGAN's spec only)
    what = (f"its weights do not fit the model its configuration describes (model.kind={model.kind}, "
            f"variant={facts['variant']}, size={facts['size']})")
    load_module_state(model, state["model"], key, path, what)
    generators = model.generators()
    if state.get("ema"):
        generators = EMA(generators, 0.0).shadow
        load_ema_weights(generators, state, key, path, what)
    model.to(device)
    generators = [g.to(device) for g in generators]
    return model, generators, ckpt_cfg, state
