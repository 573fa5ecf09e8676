"""Starting a run from a checkpoint under the run's configuration (the boundary: the run's DictConfig is compared
with the one the checkpoint stored): resuming a killed run (trainer.resume, or the run folder's own checkpoint), a
warm start's weights (init.checkpoint) and init.checkpoint=auto. Every misfit is a ConfigError naming the file and
the keys; the weights themselves are loaded by codesign/train/resume.py."""
from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from codesign.config.compare import described, differences, flat_keys
from codesign.config.runtime import to_container
from codesign.errors import ConfigError
from codesign.models.restorer import REGISTRY, restorer_kinds
from codesign.optics.materials import Material
from codesign.optics.measured import MEASURED_DEFAULTS
from codesign.train.checkpoint import CHECKPOINT_NAME, check_trained, load_checkpoint
from codesign.train.resume import resume_trainer, warm_start

log = logging.getLogger("codesign.train")
SHOWN = 4  # differing leaves named with both values before "and N more"


# Config blocks that must match between a checkpoint and the run that resumes it (trainer.* may change). The seed:
# the training continues the same whatever it is (the checkpoint restores the random state), but the final
# evaluation draws from it and the run records it as its own (issue 59).
RESUME_MUST_MATCH = ("seed", "model", "optics", "material", "mask", "sensor", "data.image_size", "data.padded_size",
                     "data.batch_size", "data.scenes", "data.folder", "data.test_fraction", "data.split_seed")
# model.name is a label: checkpoints written before it existed are named by their variant (null name = the variant)
RESUME_MAY_DIFFER = ("model.name",)


def check_resume_config(saved: dict, cfg: DictConfig, key: str, extra_keys: tuple = (), path="checkpoint") -> None:
    """A checkpoint (``path``) resumed under a different model, physics or data geometry is a ConfigError naming
    the file and the keys."""
    differ = _trained_with_other(saved, cfg, RESUME_MUST_MATCH + tuple(extra_keys), RESUME_MAY_DIFFER)
    if differ:
        raise ConfigError(key, str(path), differ + ": resume with the "
                          "same settings, or start a new run directory")



def resume_if_possible(trainer, cfg: DictConfig, run_dir: Path, extra_keys: tuple = ()) -> None:
    """Load ``trainer.resume`` or, when there is one, the run dir's own checkpoint (a killed run started again)."""
    resume = cfg.trainer.get("resume")
    auto = Path(run_dir) / CHECKPOINT_NAME
    if resume or auto.is_file():
        path = resume or auto
        state = load_checkpoint(path, "trainer.resume")
        check_trained(state, path, "trainer.resume", resume=True)
        check_resume_config(state["config"], cfg, "trainer.resume", extra_keys, path)
        resume_trainer(trainer, state, path)
        changed = trainer_changes(state["config"], cfg)
        if changed:
            log.warning("trainer.resume = %r: resumed with other training settings than the checkpoint's: %s",
                        str(path), changed)
        unused = unused_init(state["config"], cfg)
        if unused:
            log.warning("init.checkpoint = %r: not used: the run resumed from %s (step %d), whose weights replace "
                        "a warm start's (the run started from %s): to start from %r, give a new run directory",
                        unused, str(path), int(getattr(trainer, "step", 0)), _started_from(state["config"]), unused)


def unused_init(saved, cfg: DictConfig) -> str | None:
    """The init.checkpoint typed for this run when a resume ignores it: set (not null, not the default 'auto') and
    other than the one the resumed run started from (the same command line restarted says nothing). A resume
    loads the run's own weights over the warm start's, so another init.checkpoint changed nothing, silently."""
    init = cfg.get("init")
    typed = init.get("checkpoint") if init is not None else None
    if typed is None or str(typed) == "auto":
        return None
    return None if str(typed) == _started_from(saved) else str(typed)


def _started_from(saved) -> str:
    """The init.checkpoint the checkpoint's run was started with ('null': fresh weights)."""
    saved = _plain(saved)
    init = _plain(saved.get("init")) if isinstance(saved, dict) else None
    value = init.get("checkpoint") if isinstance(init, dict) else None
    return "null" if value is None else str(value)


def trainer_changes(saved, cfg: DictConfig) -> str:
    """'KEY = OLD there, NEW here; ...' for every trainer.* key of this run that differs from the checkpoint's
    (``saved``, its stored config; trainer.resume itself left out), or '': a resume may change them (more steps,
    another learning rate), and then says so, since the continued training is no longer the one started."""
    saved = _plain(saved)
    old = flat_keys(_plain(saved.get("trainer")) if isinstance(saved, dict) else None, "trainer.")
    new = flat_keys(to_container(cfg).get("trainer"), "trainer.")
    differ = differences(old, new, ("trainer.resume",))
    return described(differ, len(differ)) if differ else ""


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
    differ = _trained_with_other(state["config"], cfg, _must_match(cfg), INIT_MAY_DIFFER)
    if differ:
        raise ConfigError(key, str(path), differ + ": a warm start keeps "
                          "the network, the optics, the sensor and the image sizes (only the mask may change)")
    return warm_start(model, state, key, path)


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
    return list(dict.fromkeys(k for k, *_ in _differences(saved, cfg, must_match, may_differ)))


def _differences(saved: dict, cfg: DictConfig, must_match: tuple, may_differ: tuple) -> list[tuple[str, ...]]:
    """(must_match key, dotted leaf, checkpoint's value, this run's value) for every differing leaf under
    ``must_match``'s keys,
    ``may_differ``'s leaves left out of both; the keys in ``must_match``'s order."""
    nodes = OmegaConf.create(_with_added_keys(saved)), OmegaConf.create(to_container(cfg))
    for node in nodes:
        for dotted in may_differ:
            parent, _, leaf = dotted.rpartition(".")
            if OmegaConf.select(node, parent) is not None:
                OmegaConf.select(node, parent).pop(leaf, None)
    out = []
    for key in must_match:
        old, new = (flat_keys(_plain(OmegaConf.select(n, key)), key + ".") for n in nodes)
        out += [(key, *rest) for rest in differences(old, new)]
    return out


def _trained_with_other(saved: dict, cfg: DictConfig, must_match: tuple, may_differ: tuple) -> str:
    """'was trained with different KEYS (LEAF = A there, B here; ...)', or '' when nothing differs: what a refused
    resume or warm start says, both values of the first differing leaves named."""
    differ = _differences(saved, cfg, must_match, may_differ)
    if not differ:
        return ""
    keys = ", ".join(dict.fromkeys(k for k, *_ in differ))
    return f"was trained with different {keys} ({described([d[1:] for d in differ], SHOWN)})"
