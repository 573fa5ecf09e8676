"""``+experiment=baseline``: train a restorer (default SGAN-B) with the published mask frozen, then evaluate it."""
from __future__ import annotations

import logging
from pathlib import Path

import torch
from omegaconf import DictConfig

from codesign.config.runtime import check_seed, logging_spec, tensorboard_enabled, to_container
from codesign.io import files as io
from codesign.io.tensorboard import open_writer
from codesign.train import distributed
from codesign.train.checkpoint import CHECKPOINT_NAME
from codesign.train.data import build_simulated_data
from codesign.train.evaluation import run_evaluation
from codesign.train.mask_pool import build_mask_pool
from codesign.train.memory import check_training_fits
from codesign.experiments.resume import initial_checkpoint, load_initial_weights, resume_if_possible
from codesign.train.model_setup import build_model, build_trainer, distributed_metrics, run_metrics
from codesign.train.spec import InitSpec, TrainerSpec
from codesign.train.optim import init_weights
from codesign.experiments.specs import camera_reports, eval_settings
from codesign.experiments.protocol import Experiment

log = logging.getLogger("codesign.restoration")


EXPERIMENT = Experiment(
    summary="train a restorer (SGAN-B/E/F or a plug-in) on the frozen published mask, then evaluate it",
    first_work="build_trainer().fit",
    root_keys=("init",),
    outputs=("metrics.json", "checkpoint.pt", "evaluation.csv"),
    resumes=True,
    distributed=True,
    measured_psf=True,
)


def run(cfg: DictConfig, run_dir: Path, device: torch.device) -> float:
    """Train the configured restorer with the configured mask frozen (or over the pool of data.masks), resuming a
    killed run from its checkpoint, then evaluate it on the held-out scenes against the sensor image and classical
    Wiener; writes checkpoint.pt, metrics.json, the evaluation tables and TensorBoard events; returns the
    restorer's PSNR at alpha_l = 1e6. Steps: build, train, evaluate, report."""
    job = _build(cfg, run_dir, device)
    trainer = job["trainer"]
    history = trainer.fit(job["log_every"])
    fitted = trainer.calibrate()  # before the final scores and the evaluation, into the checkpoint (level_head)
    seconds = trainer.train_seconds  # the whole run's, across resumes
    if not job["ctx"].is_main:  # rank 0 evaluates and writes
        return None
    first, last = (history[0], history[-1]) if history else ({}, {})
    metrics = {**job["common"], **job["sampling"], **job["warm"], **job["memory"], **distributed_metrics(trainer),
               "steps": trainer.step, "seconds": seconds,
               "skipped_updates": trainer.skipped, "undone_updates": trainer.rollbacks, **trainer.divergence(),
               "vgg_loss": trainer.model.loss_status,
               "loss_first": first, "loss_last": last, **trainer.last_val, **fitted,
               "checkpoint": str(run_dir / CHECKPOINT_NAME)}
    if trainer.data.pool is not None:
        metrics["mask_pool"] = trainer.data.pool.report()
    metrics.update(run_evaluation(job["ev"], trainer.model, trainer.restoring_modules(), trainer.data, run_dir,
                                  job["seed"]))
    return _report(run_dir, trainer, metrics, job["common"])


def _build(cfg: DictConfig, run_dir: Path, device: torch.device) -> dict:
    """Every setting checked, the restorer with its starting weights (fresh, or init.checkpoint's), the data (the
    mask pool of data.masks), the reports made before any training, and the trainer, resumed when its run
    directory holds a checkpoint, with its TensorBoard writer."""
    seed = check_seed(cfg)
    spec = TrainerSpec.from_config(to_container(cfg.trainer))
    ev = eval_settings(cfg)  # every evaluation setting checked before training starts
    log_every = logging_spec(cfg).log_every
    init = InitSpec.from_config(to_container(cfg.get("init")) or {})
    model = build_model(cfg)
    init_weights(model)
    # fine-tuning: the weights of a trained checkpoint (a resumed run then loads its own checkpoint over them)
    start = initial_checkpoint(init.checkpoint, cfg)
    warm = load_initial_weights(model, start, cfg) if start else {}
    ctx = distributed.current()
    data = build_simulated_data(cfg, device, seed, ctx)
    data.use_pool(build_mask_pool(cfg, data.camera, seed))  # data.masks: one restorer for a pool of masks
    sampling = camera_reports(data.camera, cfg, log) if ctx.is_main else {}
    memory = check_training_fits(model, data, spec, device, "baseline")  # before any training
    trainer = build_trainer(cfg, model, data, run_dir, device, seed, ctx, spec)
    resume_if_possible(trainer, cfg, run_dir)
    # purge_step drops the events a killed run logged after its last checkpoint; rank 0 alone writes
    trainer.writer = open_writer(run_dir, tensorboard_enabled(cfg) and ctx.is_main, purge_step=trainer.step)
    common = run_metrics(model, device, data)
    log.info("network %s (%s, %s): generators %.2fM parameters, critics %.2fM; %d steps, batch %d, %d px padded to %d; "
             "VGG loss %s", common["network"], common["variant"], common["size"], common["parameters_generators"] / 1e6,
             common["parameters_critics"] / 1e6, spec.steps, int(cfg.data.batch_size), data.image_size,
             data.padded_size, model.loss_status)
    return {"seed": seed, "ev": ev, "log_every": log_every, "warm": warm, "ctx": ctx, "sampling": sampling,
            "memory": memory, "trainer": trainer, "common": common}


def _report(run_dir: Path, trainer, metrics: dict, common: dict) -> float:
    """metrics.json and the hyper-parameter table of the TensorBoard events; returns the restorer's PSNR at
    alpha_l = 1e6."""
    io.write_json(run_dir / "metrics.json", metrics)
    writer = trainer.writer
    method = trainer.model.method
    if writer is not None:
        writer.add_hparams({"network": common["network"], "variant": common["variant"], "size": common["size"],
                            "steps": trainer.step},
                           {f"hparam/{k}": v for k, v in metrics.items()
                            if k.startswith((f"psnr_{method}", f"ssim_{method}")) and isinstance(v, float)},
                           run_name="hparams")
        writer.close()
    return metrics.get(f"psnr_{method}_laser_1e6", float("nan"))
