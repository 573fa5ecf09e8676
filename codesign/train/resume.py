"""Resuming a killed run and loading a trained restorer from a checkpoint, with every misfit a ConfigError."""
from __future__ import annotations

import logging
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from codesign.config.runtime import to_container
from codesign.errors import ConfigError
from codesign.optics.materials import Material
from codesign.optics.measured import MEASURED_DEFAULTS
from codesign.train.checkpoint import (
    CHECKPOINT_NAME,
    check_trained,
    load_checkpoint,
    load_error,
    load_module_state,
    state_mismatch,
)
from codesign.models.restorer import REGISTRY, restorer_kinds
from codesign.train.model_setup import build_model
from codesign.train.optim import EMA

log = logging.getLogger("codesign.train")


# Config blocks that must match between a checkpoint and the run that resumes it (trainer.* may change).
RESUME_MUST_MATCH = ("model", "optics", "material", "mask", "sensor", "data.image_size", "data.padded_size",
                     "data.batch_size", "data.scenes", "data.folder", "data.test_fraction", "data.split_seed")
# model.name is a label: checkpoints written before it existed are named by their variant (null name = the variant)
RESUME_MAY_DIFFER = ("model.name",)


def check_resume_config(saved: dict, cfg: DictConfig, key: str, extra_keys: tuple = (), path="checkpoint") -> None:
    """A checkpoint (``path``) resumed under a different model, physics or data geometry is a ConfigError naming
    the file and the keys."""
    differ = _differing(saved, cfg, RESUME_MUST_MATCH + tuple(extra_keys), RESUME_MAY_DIFFER)
    if differ:
        raise ConfigError(key, str(path), "was trained with different " + ", ".join(differ) + ": resume with the "
                          "same settings, or start a new run directory")


def check_resume_steps(done, steps: int, path) -> None:
    """A resume continues a training up to trainer.steps: one asked to stop before the checkpoint's step would
    report the checkpoint's steps as this run's; a ConfigError naming both."""
    if isinstance(done, int) and not isinstance(done, bool) and done > steps:
        raise ConfigError("trainer.steps", steps, f"is fewer than the {done} steps already trained in the checkpoint "
                          f"it resumes ({path}): a resume trains on up to trainer.steps, never back: set "
                          f"trainer.steps={done} or more, or start a new run directory")


def resume_if_possible(trainer, cfg: DictConfig, run_dir: Path, extra_keys: tuple = ()) -> None:
    """Load ``trainer.resume`` or, when there is one, the run dir's own checkpoint (a killed run started again)."""
    resume = cfg.trainer.get("resume")
    auto = Path(run_dir) / CHECKPOINT_NAME
    if resume or auto.is_file():
        path = resume or auto
        state = load_checkpoint(path, "trainer.resume")
        check_trained(state, path, "trainer.resume", resume=True)
        check_resume_config(state["config"], cfg, "trainer.resume", extra_keys, path)
        problem = state_mismatch(trainer.model, state["model"])
        if problem:
            raise load_error("trainer.resume", path, "cannot be resumed: its weights do not fit this run's model",
                             problem)
        check_resume_steps(state.get("step"), trainer.spec.steps, path)
        try:
            trainer.load_state_dict(state)
        except (RuntimeError, KeyError, ValueError, TypeError, IndexError) as err:
            raise load_error("trainer.resume", path, "cannot be resumed: its state does not fit this run's model "
                             "and optimizers", err) from None
        log.info("resumed from %s at step %d (written by %d process(es), resumed by %d)", path, trainer.step,
                 int(state.get("world_size", 1)), trainer.dist.world)


# What a network's starting weights must share with the run they start (init.checkpoint): the network itself, and
# the physics and image geometry it learned to invert. The mask, the batch, the scenes and the loss weights
# (model.loss: pretraining on the reconstruction terms alone, then adding the adversarial ones) may differ.
# A network trained on the computed PSF may be fine-tuned on a measured one (optics.psf_*), and back.
INIT_MUST_MATCH = ("model", "optics", "sensor", "data.image_size", "data.padded_size")
# a warm start keeps the network: the mask may change, and with it how its surface is made, the lines reported and
# the scene's band (each only changes the blur the network is fine-tuned on, as another mask does); model.name is a
# label
# model.laser_gate_f0 and g2_base_nsr_tuned only start learned parameters, which a warm start loads;
# g2_base_pad changes what G2's base deconvolves, no parameter, which the fine-tuning then adapts to
INIT_MAY_DIFFER = ("model.loss", "model.name", "model.laser_gate_f0", "model.g2_base_nsr_tuned", "model.g2_base_pad",
                   "optics.laser_wavelengths_m", "optics.wrap_waves",
                   "optics.scene_spectrum") + tuple(f"optics.{k}" for k in MEASURED_DEFAULTS)


def _must_match(cfg: DictConfig) -> tuple[str, ...]:
    """INIT_MUST_MATCH, less the image sizes for a network that takes any size (it is trained over pixel scales and
    restores at any: codesign/models/capture.py)."""
    kind = OmegaConf.select(cfg, "model.kind") or "sgan"
    restorer_kinds()  # every restorer class registered
    if getattr(REGISTRY.get(kind), "any_size", False):
        return tuple(k for k in INIT_MUST_MATCH if not k.startswith("data."))
    return INIT_MUST_MATCH


def initial_checkpoint(value: str | None, cfg: DictConfig) -> str | None:
    """``init.checkpoint`` as the checkpoint to start from: 'auto' is the shipped restorer ('pretrained') when it fits
    this run (the same network, optics, sensor and image sizes: INIT_MUST_MATCH), else None (fresh weights), said in
    the log either way; any other value as given."""
    if value != "auto":
        return value
    try:
        state = load_checkpoint("pretrained", "init.checkpoint")
    except ConfigError as err:
        log.info("init.checkpoint=auto: %s: the restorer starts from fresh weights", err)
        return None
    differ = _differing(state["config"], cfg, _must_match(cfg), INIT_MAY_DIFFER)
    if differ:
        log.info("init.checkpoint=auto: the shipped restorer was trained with another %s than this run: the restorer "
                 "starts from fresh weights", ", ".join(differ))
        return None
    log.info("init.checkpoint=auto: the shipped restorer (checkpoint=pretrained) fits this run: the restorer starts "
             "from it")
    return "pretrained"


def load_initial_weights(model, path, cfg: DictConfig, key: str = "init.checkpoint") -> dict:
    """Start ``model`` from the weights of a checkpoint trained on another mask (a warm start): weights only (no
    optimizer, step or mask; the generators' EMA averages where the checkpoint has them, the network it reports);
    the model (but its loss weights), physics and image geometry checked against this
    run's, any difference a ConfigError naming the file and the keys. Returns what the run records: the path and
    the checkpoint's step and mask family."""
    state = load_checkpoint(path, key)
    check_trained(state, path, key)
    differ = _differing(state["config"], cfg, _must_match(cfg), INIT_MAY_DIFFER)
    if differ:
        raise ConfigError(key, str(path), "was trained with different " + ", ".join(differ) + ": a warm start keeps "
                          "the network, the optics, the sensor and the image sizes (only the mask may change)")
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


# SGAN keys added after checkpoints were written, at the values those checkpoints were trained with
SGAN_ADDED = {"g2_residual": False, "g1_base": "sensor", "g2_base": "i_b", "g2_base_nsr": 3e-2, "laser_gate": False,
              "laser_gate_f0": 1e-3, "g2_base_nsr_lasered": 3e-2, "g2_gate": False, "g2_base_nsr_tuned": False,
              "g2_base_pad": "filled", "g1_halo": False, "level_head": False, "target_level": "scene"}


# keys added with the laser lines, at the values every earlier checkpoint was trained with: the design wavelength
# alone, the 2 pi-wrapped plate, the scene at the design wavelength, the design line's LSR constraint, and the one
# material there was (fused silica)
LINES_ADDED = {"laser_wavelengths_m": None, "wrap_waves": 1, "scene_spectrum": None}
CODESIGN_ADDED = {"lsr_over": "design"}


def _material_added() -> dict:
    m = Material()
    return {"name": m.name, "formula": m.formula, "coefficients": [list(c) for c in m.coefficients],
            "valid_um": list(m.valid_um), "source": m.source}


def _with_added_keys(saved: dict) -> dict:
    """A checkpoint's configuration with the keys added since it may have been written at the values it was
    trained with: the optics keys of the measured PSF (optics.psf_*) and of the laser lines, the material, the
    co-design LSR's lines, and the SGAN's later residual options."""
    if not isinstance(saved, dict):
        return saved
    out = dict(saved)
    if isinstance(saved.get("optics"), dict):
        out["optics"] = {**MEASURED_DEFAULTS, **LINES_ADDED, **saved["optics"]}
        out.setdefault("material", _material_added())
    if isinstance(saved.get("codesign"), dict):
        out["codesign"] = {**CODESIGN_ADDED, **saved["codesign"]}
    model = saved.get("model")
    if isinstance(model, dict) and model.get("kind") == "sgan":
        out["model"] = {**SGAN_ADDED, **model}
    return out


def _plain(value):
    return OmegaConf.to_container(value) if OmegaConf.is_config(value) else value


def _differing(saved: dict, cfg: DictConfig, must_match: tuple, may_differ: tuple) -> list[str]:
    """The keys of ``must_match`` whose values differ between a checkpoint's configuration (``saved``, with the keys
    added since it was written) and this run's, ``may_differ``'s leaves left out of both."""
    nodes = OmegaConf.create(_with_added_keys(saved)), OmegaConf.create(to_container(cfg))
    for node in nodes:
        for dotted in may_differ:
            parent, _, leaf = dotted.rpartition(".")
            if OmegaConf.select(node, parent) is not None:
                OmegaConf.select(node, parent).pop(leaf, None)
    return [k for k in must_match if _plain(OmegaConf.select(nodes[0], k)) != _plain(OmegaConf.select(nodes[1], k))]


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
