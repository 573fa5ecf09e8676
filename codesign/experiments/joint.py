"""``+experiment=joint``: mask and SGAN trained end to end, then compared with the published mask + an SGAN trained
with the same steps and seed, on the same test scenes and laser strengths.

Run directory: checkpoint.pt, metrics.json, learned_mask.json (seeds mask.init=PATH), phase / PSF / MTF figures of
the learned and the published mask, the evaluation tables and panels, and TensorBoard events; the published
comparison lives in published/ (its own checkpoint, evaluation and events: a second run in TensorBoard).
A killed run started again on the same run directory (hydra.run.dir=...) resumes where it stopped.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from codesign.config.runtime import check_seed, logging_spec, tensorboard_enabled, to_container
from codesign.design.check import camera_sampling_report, recheck_gain, report_sampling, sampling_of
from codesign.design.limits import MTFLimit
from codesign.train.lsr_constraint import CodesignSpec, LSRConstraint
from codesign.errors import ConfigError
from codesign.design.merit import MaskMonitor, published_reference
from codesign.fab.laser_lines import lines_summary, log_lines, run_lines
from codesign.optics.masks.records import write_record
from codesign.io import files as io
from codesign.io import plots
from codesign.io.tensorboard import open_writer
from codesign.optics import HalfRingMask, circular_mtf
from codesign.optics.masks import published_mask_config
from codesign.train import distributed
from codesign.train.base_tuning import tune_base_nsr
from codesign.train.checkpoint import CHECKPOINT_NAME
from codesign.train.data import SimulatedData, build_simulated_data
from codesign.train.evaluation import conditions, run_evaluation
from codesign.train.mask_codesign import MaskCodesign
from codesign.train.memory import check_training_fits
from codesign.experiments.resume import initial_checkpoint, load_initial_weights, resume_if_possible
from codesign.train.model_setup import build_model, build_trainer, distributed_metrics, run_metrics
from codesign.train.spec import InitSpec, TrainerSpec
from codesign.train.summary import comparison_figure, joint_summary, restorer_scores
from codesign.train.optim import init_weights
from codesign.experiments.main_job import IMAGES_FILE, run_protocol, save_images
from codesign.experiments.specs import eval_settings, material_of, metrics_spec
from codesign.experiments.protocol import Experiment

log = logging.getLogger("codesign.joint")


EXPERIMENT = Experiment(
    summary="the main job: mask and restorer trained end to end, compared with the published system",
    first_work="_train",
    root_keys=("codesign", "init", "search"),
    outputs=("metrics.json", "checkpoint.pt", "learned_mask.json", "evaluation.csv", "mtf.png"),
    resumes=True,
    distributed=True,
    smoke={"search.max_evals": 8, "search.polish_max_evals": 4, "codesign.finetune_steps": 2},
)

PUBLISHED_DIR = "published"
COMPARED = "laser_1e6"  # the condition whose restorations the comparison figure shows side by side


def _train(trainer, cfg, run_dir: Path, log_every: int, label: str, calibrate: bool = True) -> dict:
    resume_if_possible(trainer, cfg, run_dir, extra_keys=("codesign",))
    main = trainer.dist.is_main  # rank 0 alone writes events and validates
    trainer.writer = open_writer(run_dir, tensorboard_enabled(cfg) and main, purge_step=trainer.step)
    if trainer.step == 0 and main:  # the untrained network's validation scores: the reference for "it learned"
        trainer.record["start"] = {f"{k.replace('/', '_')}_start": v
                                   for k, v in trainer.validate(images=True).items()}
    log.info("%s: training from step %d to %d", label, trainer.step, trainer.spec.steps)
    trainer.fit(log_every)
    # the fitted parts (model.level_head) of a network that will be evaluated, before its final scores
    fitted = trainer.calibrate() if calibrate else {}
    end = {f"{k.replace('/', '_')}_end": v for k, v in trainer.last_val.items()}
    # a resumed run's record is the whole run's: its start scores and seconds come from the checkpoint
    return {"seconds": trainer.train_seconds, **trainer.record.get("start", {}), **end, **trainer.divergence(),
            **fitted}


def _mask_outputs(monitor: MaskMonitor, system, mask, run_dir: Path, prefix: str, psf0: np.ndarray) -> dict:
    """Refined figures of merit of a mask with its physical limit (lsr_limit at its mtf_mean, lsr_over_limit), and
    its phase and PSF figures (``prefix``_*.png; ``psf0``: the uncoded PSF they are shown against)."""
    values, arrays = monitor.measure(mask, refine=True)
    energy = float(arrays["psf"].sum())
    values["lsr_limit"] = MTFLimit(system, monitor.band).lsr_limit(values["mtf_mean"], energy)
    values["lsr_over_limit"] = values["lsr"] / values["lsr_limit"]
    spec = system.spec
    np_ = {k: v.detach().cpu().numpy() for k, v in arrays.items()}
    io.save_figure(run_dir / f"{prefix}_phase.png", plots.phase_figure(
        np_["phase"], system.grid.aperture.cpu().numpy(), spec.pupil_pitch_m, f"{prefix} mask: pupil phase"))
    io.save_figure(run_dir / f"{prefix}_psf_log.png", plots.psf_figure(
        np_["psf"], psf0, spec.focal_pitch_m, f"{prefix} mask: PSF, LSR = {values['lsr']:.4g}"))
    return {**values, "mtf_radial": np_["mtf_radial"]}


def _save_learned_mask(mask, spec, run_dir: Path, values: dict) -> dict:
    """learned_phase.npy and learned_mask.json (the mask's record: seeds mask.init=PATH); returns the r_n / theta_n
    metrics of a half-ring mask (empty for other families)."""
    io.save_npy(run_dir / "learned_phase.npy", mask.phase().detach())
    record = write_record(run_dir / "learned_mask.json", mask, spec,
                          {k: values[k] for k in ("lsr", "lsr_smooth", "mtf_mean")})
    if not isinstance(mask, HalfRingMask):
        return {}
    return {"r_n": record["r"], "theta_n": record["theta"]}


def run(cfg: DictConfig, run_dir: Path, device: torch.device) -> float:
    """codesign.protocol=codesign: the main job's stages (codesign/experiments/main_job.py), each stage's training
    a run_single; single: one run_single."""
    cs = CodesignSpec.from_config(to_container(cfg.get("codesign")) or {})
    if cfg.data.get("masks") is not None:
        raise ConfigError("data.masks", to_container(cfg.data.masks), "trains one restorer over a pool of frozen "
                          "masks (+experiment=baseline data.masks=[...]); a joint run trains one mask: leave it null "
                          "and warm-start from such a restorer with init.checkpoint=PATH")
    if cs.protocol == "single":
        return run_single(cfg, run_dir, device)
    return run_protocol(cfg, run_dir, device, run_single)


def run_single(cfg: DictConfig, run_dir: Path, device: torch.device, evaluate: bool = True) -> float:
    """One joint training of the configured mask (its published comparison when codesign.compare_published); then,
    when ``evaluate``, the evaluation on the held-out scenes (without: metrics.json holds the training's figures,
    the pretraining stages of the codesign protocol). Steps: build, train (and the published comparison), report
    the masks, evaluate."""
    job = _build(cfg, run_dir, device)
    timing = _train(job.trainer, cfg, run_dir, job.log_every, "joint", calibrate=evaluate)
    job.camera.set_trainable(False)
    job.camera.invalidate()
    # every rank trains the published comparison too; evaluations and files then come from rank 0 alone
    published = _published_train(cfg, job.published_cfg, job.init, job.spec, job.trainer.step, job.seed, device,
                                 run_dir, job.log_every, job.ctx) if job.cs.compare_published else None
    if not job.ctx.is_main:
        return None
    metrics = _mask_report(job, run_dir, timing)
    if not evaluate:
        io.write_json(run_dir / "metrics.json", metrics)
        _hparams(job.trainer.writer, cfg, metrics, job.model.method)
        log.info("joint: lsr %.4g, mtf_mean %.4g after %d steps (not evaluated); wrote %s", metrics["lsr"],
                 metrics["mtf_mean"], metrics["steps"], run_dir)
        return float("nan")
    return _evaluate(job, run_dir, metrics, published)


@dataclass
class _Joint:
    """What a joint run builds before it trains (run_single's first step): its settings, the restorer and its
    starting weights, the simulated data and camera, the published reference mask, the LSR ceiling and the trainer
    with the mask's co-design component."""

    cfg: DictConfig
    seed: int
    spec: TrainerSpec
    cs: CodesignSpec
    ms: object
    ev: dict
    log_every: int
    published_cfg: dict
    init: InitSpec
    model: object
    warm: dict
    ctx: object
    data: SimulatedData
    reference: object
    monitor: MaskMonitor
    lines: object
    lsr_max: float
    lsr_max_from: str
    start: dict
    mask: MaskCodesign | None = None
    trainer: object = None
    common: dict = field(default_factory=dict)

    @property
    def camera(self):
        return self.data.camera

    @property
    def system(self):
        return self.data.camera.system


def _build(cfg: DictConfig, run_dir: Path, device: torch.device) -> _Joint:
    """Every setting checked, the network with its starting weights, the data, the LSR ceiling and its checks, the
    Wiener base tuned (fresh weights), the mask's co-design component and the trainer."""
    seed = check_seed(cfg)
    spec = TrainerSpec.from_config(to_container(cfg.trainer))
    cs = CodesignSpec.from_config(to_container(cfg.get("codesign")) or {})
    ms = metrics_spec(cfg)
    ev = eval_settings(cfg)  # every setting checked before any training
    log_every = logging_spec(cfg).log_every
    published_cfg = published_mask_config(to_container(cfg.mask))
    init = InitSpec.from_config(to_container(cfg.get("init")) or {})
    model, warm = _network(cfg, init, seed)
    ctx = distributed.current()
    data = build_simulated_data(cfg, device, seed, ctx)
    camera, system = data.camera, data.camera.system
    reference = published_reference(to_container(cfg.mask), system)
    monitor = MaskMonitor(system, reference, ms.mtf_band, ms.lsr_p, ms.lsr_grids)
    lines = run_lines(material_of(cfg), system, "codesign.lsr_over" if cs.lsr_over == "wavelengths" else None)
    constrained = lines if cs.lsr_over == "wavelengths" else None
    lsr_max, lsr_max_from = _lsr_max(cs, monitor, system, camera.mask, reference, constrained)
    start = check_training_fits(model, data, spec, device, "joint")  # before any training
    if ctx.is_main:  # warned about before any training
        sampling = camera_sampling_report(camera, ms.mtf_band, log, "the start mask")
        start.update(phase_resolved_start=sampling["phase_resolved"], phase_sampling_start=sampling["phase_sampling"],
                     **_check_lsr_max(lsr_max, cs, monitor, system, camera.mask, constrained))
    if not warm:
        start.update(_tune_base(model, data, ev))
    job = _Joint(cfg, seed, spec, cs, ms, ev, log_every, published_cfg, init, model, warm, ctx, data, reference,
                 monitor, lines, lsr_max, lsr_max_from, start)
    job.mask = MaskCodesign(camera=camera, spec=cs, lsr_max=lsr_max, lsr_p=ms.lsr_p, lsr_grids=ms.lsr_grids,
                            steps=spec.steps, device=device, monitor=monitor, dist=ctx, lines=constrained)
    job.trainer = build_trainer(cfg, model, data, run_dir, device, seed, ctx, spec, codesign=job.mask)
    job.common = run_metrics(model, device, data)
    _log_start(job)
    job.trainer.steps_after = spec.steps if cs.compare_published else 0  # the ETA covers the published training too
    return job


def _log_start(job: _Joint) -> None:
    """The run's one line before training: network, mask, ceiling, steps and sizes."""
    common, cs, spec, data = job.common, job.cs, job.spec, job.data
    log.info("joint: network %s (%s, %s) generators %.2fM parameters; mask %s (%d parameters, lr %.3g, frozen for "
             "%d steps); lsr_max %.4g (%s); %d steps, batch %d, %d px padded to %d", common["network"],
             common["variant"], common["size"], common["parameters_generators"] / 1e6,
             to_container(job.cfg.mask)["kind"], sum(p.numel() for p in job.camera.mask.parameters()), cs.mask_lr,
             cs.warmup_steps(spec.steps), job.lsr_max, job.lsr_max_from, spec.steps, int(job.cfg.data.batch_size),
             data.image_size, data.padded_size)


def _mask_report(job: _Joint, run_dir: Path, timing: dict) -> dict:
    """After training (rank 0): the learned and the published mask measured, re-checked and drawn (phase, PSF, MTF
    figures, learned_mask.json), over the laser lines when there are some; returns metrics.json's entries so far."""
    system, mask, monitor, ms, cs = job.system, job.camera.mask, job.monitor, job.ms, job.cs
    steps = job.trainer.step
    with torch.no_grad():
        psf0 = system.uncoded_psf().cpu().numpy()
    learned = _mask_outputs(monitor, system, mask, run_dir, "learned", psf0)
    recheck = recheck_gain(mask, job.reference, system.spec, ms.mtf_band, ms.recheck_tolerance, log)
    verified = recheck["recheck"]["learned"]  # its design and fine-grid evaluations answer the sampling question
    sampling = report_sampling(sampling_of(verified["design"], verified["fine"]), log, "the learned mask")
    base = _mask_outputs(monitor, system, job.reference, run_dir, "published", psf0)
    rings = _save_learned_mask(mask, system.spec, run_dir, learned)
    freqs = monitor.radial.freqs.cpu().numpy()
    io.save_figure(run_dir / "mtf.png", plots.mtf_figure(
        freqs, {"learned mask": learned.pop("mtf_radial"), "published mask": base.pop("mtf_radial"),
                "analytic circular pupil": circular_mtf(torch.from_numpy(freqs)).numpy()},
        ms.mtf_band, f"radial MTF after {steps} joint steps"))
    trainer = job.trainer
    metrics = {**job.common, **distributed_metrics(trainer), **job.mask.record(), "steps": steps, **timing,
               "lsr_max": job.lsr_max, "lsr_max_from": job.lsr_max_from, **job.start, **sampling,
               **job.warm,
               "lsr_constraint_met": learned["lsr_smooth"] <= job.lsr_max * (1 + cs.guard_tolerance),
               "skipped_updates": trainer.skipped, "undone_updates": trainer.rollbacks,
               "vgg_loss": job.model.loss_status, "mask_kind": to_container(job.cfg.mask)["kind"],
               **learned, **{f"{k}_published": v for k, v in base.items()}, **mask.summary(), **rings,
               **recheck, "checkpoint": str(run_dir / CHECKPOINT_NAME)}
    if job.lines is not None:
        metrics["lsr_over"] = cs.lsr_over
        metrics["laser_lines"] = summary = lines_summary(job.lines, {"learned": mask.phase().detach(),
                                                                     "published": job.reference.phase().detach()},
                                                         mask.plate_cell_m)
        for name in ("learned", "published"):
            log_lines(summary, name, f"{name} mask")
    return metrics


def _evaluate(job: _Joint, run_dir: Path, metrics: dict, published) -> float:
    """The learned system (and the published one, when trained) evaluated on the held-out scenes, the comparison
    figure, metrics.json and the summary; returns the learned system's mean PSNR."""
    model, ev, seed = job.model, job.ev, job.seed
    keep = (COMPARED,) if COMPARED in conditions(ev["lasers"], ev["stages"]) else ()
    joint_eval = run_evaluation(ev, model, job.trainer.restoring_modules(), job.data, run_dir, seed, keep)
    for key in ("evaluation", "evaluation_scenes", "evaluation_per_scene_psnr_matched"):
        metrics[key] = joint_eval[key]
    if keep:  # the first scenes' restorations at COMPARED, for the main job's figure of every system
        save_images(run_dir / IMAGES_FILE, joint_eval["images"][COMPARED], model.method)
    metrics.update(restorer_scores(joint_eval["evaluation"], model.method))  # with or without the published comparison
    if published is not None:
        extra, pub_images = _published_evaluation(*published, run_dir, ev, seed, keep)
        metrics.update(extra)
        if keep and pub_images:
            io.save_figure(run_dir / f"compare_{COMPARED}.png", comparison_figure(
                joint_eval["images"][COMPARED], pub_images[COMPARED], model.method, COMPARED, network=model.spec.name,
                names=joint_eval["evaluation_scenes"], tables={"learned": joint_eval["evaluation"][COMPARED],
                                                               "published": extra["evaluation_published"][COMPARED]}))
    io.write_json(run_dir / "metrics.json", metrics)
    _hparams(job.trainer.writer, job.cfg, metrics, model.method)
    if published is not None:
        print(joint_summary({**metrics, "seed": seed}, model.method), flush=True)
    else:
        log.info("joint: lsr %.4g (published %.4g), mtf_mean %.4g (published %.4g); no published comparison "
                 "(codesign.compare_published=false)", metrics["lsr"], metrics["lsr_published"],
                 metrics["mtf_mean"], metrics["mtf_mean_published"])
    log.info("wrote %s", run_dir)
    return metrics.get("psnr", float("nan"))


def _tune_base(model, data, ev: dict) -> dict:
    """model.g2_base_nsr_tuned on fresh weights: the Wiener base's nsr tuned to this mask (codesign/train/
    base_tuning.py) on as many training crops as the evaluation tunes its floors on; what metrics.json records."""
    if not getattr(getattr(model, "spec", None), "g2_base_nsr_tuned", False):
        return {}
    return {"g2_base_nsr_tuned": tune_base_nsr(model, data, ev["tuning"])}


def _network(cfg, init: InitSpec, seed: int) -> tuple:
    """The restorer with its starting weights: seeded fresh ones, or a warm start's (init.checkpoint); and what the
    run records of the latter."""
    torch.manual_seed(seed)
    model = build_model(cfg)
    init_weights(model)
    start = initial_checkpoint(init.checkpoint, cfg)
    warm = load_initial_weights(model, start, cfg) if start else {}
    return model, warm


def _lsr_max(cs: CodesignSpec, monitor: MaskMonitor, system, mask, reference, lines=None) -> tuple[float, str]:
    """The smooth-LSR ceiling (codesign.lsr_max: CodesignSpec.lsr_max_value) and where it comes from (``lines``: the
    worst of these lines)."""
    def measured(which):
        return lambda: LSRConstraint(cs, system, 1.0, monitor.p, monitor.grids, lines).measure(which)

    published = measured(reference) if lines is not None else lambda: monitor.reference[0]["lsr_smooth"]
    return cs.lsr_max_value(published, measured(mask),
                            "smooth LSR" + ("" if lines is None else " (worst laser line)"))


# codesign.lsr_max this many times below the start mask's smooth LSR draws a warning: the constraint then
# dominates the loss from the first step (a typed 1e-9 for 1e-3 is the usual cause)
LSR_MAX_FAR = 10.0


def _check_lsr_max(lsr_max: float, cs: CodesignSpec, monitor: MaskMonitor, system, mask, lines=None) -> dict:
    """Warn at the start when codesign.lsr_max cannot be reached by any phase-only mask on this window (below the
    light spread evenly over it: MTFLimit.lsr_limit(0)), or lies far below the start mask's smooth LSR."""
    start = LSRConstraint(cs, system, 1.0, monitor.p, monitor.grids, lines).measure(mask)
    floor = MTFLimit(system, monitor.band).lsr_limit(0.0)
    if lsr_max < floor:
        log.warning("codesign.lsr_max = %.3g is below what any phase-only mask can reach on this %d-sample window "
                    "(%.3g: the light spread evenly over it, MTF 0): the constraint can never be met; the start "
                    "mask's smooth LSR is %.3g (%.3gx over it)", lsr_max, system.spec.focal_n, floor, start,
                    start / lsr_max)
    elif start > LSR_MAX_FAR * lsr_max:
        log.warning("codesign.lsr_max = %.3g is %.3gx below the start mask's smooth LSR %.3g: the constraint "
                    "dominates the loss from the first step and the mask is pulled toward it at any cost in MTF "
                    "(give a ceiling near the start, e.g. codesign.lsr_max=start)", lsr_max, start / lsr_max, start)
    return {"lsr_smooth_start": start, "lsr_max_over_start": lsr_max / start, "lsr_max_reachable": lsr_max >= floor}


def _published_train(cfg, published_cfg, init, spec, steps, seed, device, run_dir, log_every, ctx) -> tuple:
    """Train the same restorer on the published mask with the same steps, seed, data draws and starting weights:
    (model, trainer, data, timing) for _published_evaluation."""
    sub = run_dir / PUBLISHED_DIR
    pub_cfg = OmegaConf.create(to_container(cfg))
    pub_cfg.mask = published_cfg
    pub_spec = TrainerSpec.from_config({**to_container(cfg.trainer), "steps": steps, "time_budget_s": None,
                                        "resume": None})
    model, warm = _network(pub_cfg, init, seed)  # the same initial weights as the joint network
    data = build_simulated_data(pub_cfg, device, seed, ctx)
    if not warm:
        _tune_base(model, data, eval_settings(pub_cfg))
    trainer = build_trainer(pub_cfg, model, data, sub, device, seed, ctx, pub_spec)
    timing = _train(trainer, pub_cfg, sub, log_every, "published mask")
    return model, trainer, data, timing


def _published_evaluation(model, trainer, data, timing: dict, run_dir, ev, seed, keep) -> tuple:
    """Evaluate the published-mask restorer (rank 0): (its metrics entries with the _published suffix, the images of
    the ``keep`` conditions)."""
    sub = run_dir / PUBLISHED_DIR
    result = run_evaluation(ev, model, trainer.restoring_modules(), data, sub, seed, keep)
    images = result.pop("images", {})
    io.write_json(sub / "metrics.json", {"steps": trainer.step, **timing, **result})
    if trainer.writer is not None:
        trainer.writer.close()
    return {**{f"{k}_published": v for k, v in timing.items()}, "evaluation_published": result["evaluation"],
            "evaluation_per_scene_psnr_matched_published": result["evaluation_per_scene_psnr_matched"],
            **restorer_scores(result["evaluation"], model.method, "_published")}, images


def _hparams(writer, cfg, metrics: dict, method: str | None = None) -> None:
    if writer is None:
        return
    hp = {"network": metrics["network"], "variant": metrics["variant"], "size": metrics["size"],
          "mask": metrics["mask_kind"], "steps": metrics["steps"], "lsr_max": metrics["lsr_max"]}
    keys = ("lsr", "lsr_published", "lsr_smooth", "mtf_mean", "mtf_mean_published", "psnr", "psnr_published", "ssim",
            "ssim_published", "psnr_matched", "psnr_matched_published")
    writer.add_hparams(hp, {f"hparam/{k}": float(metrics[k]) for k in keys if k in metrics}, run_name="hparams")
    # the test scores per condition (laser strength alpha_l, robustness stage) as scalars too, at the last step:
    # test/<metric>/<condition> (learned system), test_published/<metric>/<condition> (the published one)
    for prefix, key in (("test", "evaluation"), ("test_published", "evaluation_published")):
        for cond, table in (metrics.get(key) or {}).items():
            row = table.get(method) if method in table else list(table.values())[-1]  # the restorer: the last
            for metric in ("psnr", "psnr_matched", "ssim", "ssim_matched"):
                v = (row or {}).get(metric)
                if isinstance(v, (int, float)) and math.isfinite(v):
                    writer.add_scalar(f"{prefix}/{metric}/{_condition_tag(cond)}", float(v), metrics["steps"])
    writer.close()


def _condition_tag(cond: str) -> str:
    """laser_1e6 -> alpha_l_1e6 (laser_0 -> alpha_l_0); robustness stages keep their names (H1 -> stage_H1)."""
    return f"alpha_l_{cond[len('laser_'):]}" if cond.startswith("laser_") else f"stage_{cond}"
