"""``+experiment=baseline`` (train an SGAN with the published mask frozen, then evaluate) and
``+experiment=evaluate checkpoint=PATH``."""
from __future__ import annotations

import logging
import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from codesign import quality
from codesign.data.params import LASER_STRENGTHS, PRESETS, ROBUSTNESS_STAGES, _laser_name
from codesign.engine import distributed, io
from codesign.engine.checkpoint import (CHECKPOINT_NAME, check_trained, load_checkpoint, load_error,
                                       load_module_state, state_mismatch)
from codesign.engine.evaluate import Evaluator, conditions, evaluate, flat_summary
from codesign.engine.monitor import log_summary, open_writer, tensorboard_enabled
from codesign.engine.pipeline import RestorationData
from codesign.engine.train_spec import LossWeights, TrainerSpec
from codesign.engine.trainer import EMA, RestorationTrainer, init_weights
from codesign.errors import ConfigError, require_choice, require_list, require_number, require_numbers, unknown_keys
from codesign.models import build_sgan, parameter_count

log = logging.getLogger("codesign.restoration")


def _container(node) -> dict:
    return OmegaConf.to_container(node, resolve=True) if node is not None else {}


def build_model(cfg: DictConfig):
    model_cfg = _container(cfg.model)
    model = build_sgan(model_cfg)
    model.spec.check_input_size(int(cfg.data.padded_size))
    return model


def loss_weights(cfg: DictConfig) -> LossWeights:
    return LossWeights.from_config(_container(cfg.model.get("loss")) or {})


EVALUATE_KEYS = ("split", "max_scenes", "laser_strengths", "stages", "tuning_size", "batch_size", "laser_angle_rad",
                 "lpips_weights", "dists_weights")


def eval_settings(cfg: DictConfig) -> dict:
    """Validate ``evaluate.*`` (and load LPIPS / DISTS when given), before any training or simulation."""
    ev = cfg.get("evaluate") or {}
    unknown_keys("evaluate", ev, EVALUATE_KEYS)
    split = require_choice("evaluate.split", ev.get("split", "test"), ("test", "train", "all"))
    max_scenes = require_number("evaluate.max_scenes", ev.get("max_scenes", 8), lo=1, hi=100000, integer=True)
    allowed = ", ".join(f"{a:g}" for a in LASER_STRENGTHS)
    lasers = require_list("evaluate.laser_strengths", ev.get("laser_strengths", LASER_STRENGTHS),
                          f"must be a list of the paper's strengths {allowed}")
    for i, a in enumerate(lasers):
        a = require_number(f"evaluate.laser_strengths[{i}]", a, lo=0)
        if _laser_name(float(a)) not in PRESETS or PRESETS[_laser_name(float(a))]["alpha_l"] != float(a):
            raise ConfigError(f"evaluate.laser_strengths[{i}]", a, f"must be one of the paper's strengths {allowed}")
    stages = require_list("evaluate.stages", ev.get("stages", list(ROBUSTNESS_STAGES)),
                          f"must be a list of robustness stages from {', '.join(ROBUSTNESS_STAGES)} (or [])")
    for i, st in enumerate(stages):
        require_choice(f"evaluate.stages[{i}]", st, tuple(ROBUSTNESS_STAGES))
    tuning = require_number("evaluate.tuning_size", ev.get("tuning_size", 8), lo=1, hi=256, integer=True)
    batch = require_number("evaluate.batch_size", ev.get("batch_size", 8), lo=1, hi=4096, integer=True)
    angle = ev.get("laser_angle_rad")
    if angle is not None:
        angle = require_numbers("evaluate.laser_angle_rad", angle, "must be [n_u, n_v] in radians, or null", 2)
    return {"split": split, "max_scenes": max_scenes, "lasers": [float(a) for a in lasers], "stages": stages,
            "tuning": tuning, "batch_size": batch,
            "perceptual": quality.perceptual_metrics(ev.get("lpips_weights"), ev.get("dists_weights")),
            "overrides": {} if angle is None else {"laser_angle_rad": angle}}


def run_evaluation(ev: dict, model, generators, data: RestorationData, run_dir: Path, seed: int) -> dict:
    """Tune baselines on the training distribution, then score every method on the chosen split."""
    names = data.source.split_names(ev["split"])[: ev["max_scenes"]]
    if not names:
        raise ConfigError("evaluate.split", ev["split"], "has no scenes in this data source")
    scenes = data.source.fixed_batch(names, data.sim.scene_size)
    evaluator = Evaluator(model, generators, data, ev["perceptual"], ev["batch_size"])
    calib = evaluator.tune(data.validation_batch(ev["tuning"]))
    presets = conditions(ev["lasers"], ev["stages"])
    results = evaluate(evaluator, scenes, names, presets, seed, run_dir, ev["overrides"])
    perceptual = {k: ("available" if callable(v) else v) for k, v in ev["perceptual"].items()}
    return {"evaluation": results, "evaluation_scenes": names, "baseline_calibration": calib,
            "perceptual_metrics": perceptual, **flat_summary(results)}


def distributed_metrics(trainer) -> dict:
    """How a run was spread over processes, and the largest parameter difference between ranks found."""
    ctx = trainer.dist
    return {"world_size": ctx.world, "global_batch": int(trainer.data.sampler.batch_size),
            "parameters_max_rank_difference": trainer.replica_diff}


def _common_metrics(cfg, model, device) -> dict:
    return {"variant": model.spec.variant, "size": model.spec.size, "device": str(device),
            "threads": torch.get_num_threads(), "torch": torch.__version__,
            "parameters_generators": sum(parameter_count(g) for g in model.generators()),
            "parameters_critics": sum(parameter_count(d) for d in model.discriminators()),
            "image_size": int(cfg.data.image_size), "padded_size": int(cfg.data.padded_size)}


# Config blocks that must match between a checkpoint and the run that resumes it (trainer.* may change).
RESUME_MUST_MATCH = ("model", "optics", "mask", "sensor", "data.image_size", "data.padded_size",
                     "data.batch_size", "data.scenes", "data.folder", "data.test_fraction", "data.split_seed")


def check_resume_config(saved: dict, cfg: DictConfig, key: str, extra_keys: tuple = (), path="checkpoint") -> None:
    """A checkpoint (``path``) resumed under a different model, physics or data geometry is a ConfigError naming
    the file and the keys."""
    saved_cfg, current = OmegaConf.create(saved), OmegaConf.create(_container(cfg))
    differ = []
    for dotted in RESUME_MUST_MATCH + tuple(extra_keys):
        a, b = OmegaConf.select(saved_cfg, dotted), OmegaConf.select(current, dotted)
        a = OmegaConf.to_container(a) if OmegaConf.is_config(a) else a
        b = OmegaConf.to_container(b) if OmegaConf.is_config(b) else b
        if a != b:
            differ.append(dotted)
    if differ:
        raise ConfigError(key, str(path), "was trained with different " + ", ".join(differ) + ": resume with the "
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
        problem = state_mismatch(trainer.model, state["model"])
        if problem:
            raise load_error("trainer.resume", path, "cannot be resumed: its weights do not fit this run's model",
                             problem)
        try:
            trainer.load_state_dict(state)
        except (RuntimeError, KeyError, ValueError, TypeError, IndexError) as err:
            raise load_error("trainer.resume", path, "cannot be resumed: its state does not fit this run's model "
                             "and optimizers", err) from None
        log.info("resumed from %s at step %d (written by %d process(es), resumed by %d)", path, trainer.step,
                 int(state.get("world_size", 1)), trainer.dist.world)


def apply_checkpoint_mask(mask, state: dict, path="checkpoint", key: str = "checkpoint") -> None:
    """A co-design checkpoint carries its learned mask: load it over the configured one."""
    if state.get("mask") is not None:
        load_module_state(mask, state["mask"], key, path, f"its learned mask does not fit the {type(mask).__name__} "
                          "of its configuration")


def run_baseline(cfg: DictConfig, run_dir: Path, device: torch.device) -> float:
    seed = int(cfg.get("seed", 0))
    spec = TrainerSpec.from_config(_container(cfg.trainer))
    weights = loss_weights(cfg)
    ev = eval_settings(cfg)  # every evaluation setting checked before training starts
    log_every = require_number("logging.log_every", cfg.get("logging", {}).get("log_every", 10), lo=1,
                               integer=True)
    model = build_model(cfg)
    init_weights(model)
    ctx = distributed.current()
    data = RestorationData(cfg, device, seed, ctx)
    trainer = RestorationTrainer(model, data, spec, weights, run_dir, device, _container(cfg), None, seed, ctx)
    resume_if_possible(trainer, cfg, run_dir)
    # purge_step drops the events a killed run logged after its last checkpoint; rank 0 alone writes
    trainer.writer = open_writer(run_dir, tensorboard_enabled(cfg) and ctx.is_main, purge_step=trainer.step)
    common = _common_metrics(cfg, model, device)
    log.info("%s (%s): generators %.2fM parameters, critics %.2fM; %d steps, batch %d, %d px padded to %d; "
             "VGG loss %s", model.spec.variant, model.spec.size, common["parameters_generators"] / 1e6,
             common["parameters_critics"] / 1e6, spec.steps, int(cfg.data.batch_size), data.image_size,
             data.padded_size, trainer.vgg_status)
    t0 = time.perf_counter()
    history = trainer.fit(log_every)
    seconds = time.perf_counter() - t0
    if not ctx.is_main:  # rank 0 evaluates and writes
        return None
    first, last = (history[0], history[-1]) if history else ({}, {})
    metrics = {**common, **distributed_metrics(trainer), "steps": trainer.step, "seconds": seconds,
               "skipped_updates": trainer.skipped, "vgg_loss": trainer.vgg_status,
               "loss_first": first, "loss_last": last, **getattr(trainer, "last_val", {}),
               "checkpoint": str(run_dir / CHECKPOINT_NAME)}
    metrics.update(run_evaluation(ev, model, trainer.restoring_modules(), data, run_dir, seed))
    io.write_json(run_dir / "metrics.json", metrics)
    writer = trainer.writer
    if writer is not None:
        writer.add_hparams({"variant": model.spec.variant, "size": model.spec.size, "steps": trainer.step},
                           {f"hparam/{k}": v for k, v in metrics.items()
                            if k.startswith(("psnr_sgan", "ssim_sgan")) and isinstance(v, float)},
                           run_name="hparams")
        writer.close()
    return metrics.get("psnr_sgan_laser_1e6", float("nan"))


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
    what = (f"its weights do not fit the model its configuration describes (model.variant={model.spec.variant}, "
            f"model.size={model.spec.size})")
    load_module_state(model, state["model"], key, path, what)
    generators = model.generators()
    if state.get("ema"):
        ema, states = EMA(generators, 0.0), state["ema"]
        if not isinstance(states, list) or len(states) != len(generators):
            n = len(states) if isinstance(states, list) else "no list of"
            raise load_error(key, path, what, f"its EMA holds {n} generator state(s), the model has "
                             f"{len(generators)} generators")
        for shadow, st in zip(ema.shadow, states):
            load_module_state(shadow, st, key, path, what + " (EMA weights)")
        generators = ema.shadow
    model.to(device)
    generators = [g.to(device) for g in generators]
    return model, generators, ckpt_cfg, state


def merged_eval_config(cfg: DictConfig, ckpt_cfg: DictConfig, typed: frozenset[str]) -> DictConfig:
    """The checkpoint's physics, model and data split, with the scene-source keys typed on this command line
    (``typed``: e.g. data.scenes, data.folder) and this run's ``evaluate`` block. Untyped data keys keep the
    checkpoint's values, so the test split is the one held out during training."""
    merged = OmegaConf.create(OmegaConf.to_container(ckpt_cfg, resolve=True))
    for key in ("scenes", "folder", "test_fraction", "split_seed", "cache_mb"):
        if f"data.{key}" in typed or "data" in typed:
            merged.data[key] = cfg.data.get(key)
    merged.evaluate = cfg.get("evaluate")
    return merged


def run_evaluate(cfg: DictConfig, run_dir: Path, device: torch.device) -> float:
    from codesign.engine.experiments import explicit_keys

    path = cfg.get("checkpoint")
    if not path:
        raise ConfigError("checkpoint", path, "give the trained model: +experiment=evaluate checkpoint=PATH")
    ev = eval_settings(cfg)
    model, generators, ckpt_cfg, state = load_trained(path, device)
    merged = merged_eval_config(cfg, ckpt_cfg, explicit_keys())
    seed = int(cfg.get("seed", 0))
    data = RestorationData(merged, device, seed)
    apply_checkpoint_mask(data.mask, state, path)
    data.refresh_psf()
    metrics = {**_common_metrics(merged, model, device), "checkpoint": str(path), "steps": int(state["step"])}
    metrics.update(run_evaluation(ev, model, generators, data, run_dir, seed))
    io.write_json(run_dir / "metrics.json", metrics)
    log_summary(open_writer(run_dir, tensorboard_enabled(cfg)),
                {"variant": model.spec.variant, "size": model.spec.size, "checkpoint": str(path)}, metrics)
    return metrics.get("psnr_sgan_laser_1e6", float("nan"))
