"""The main job's protocol (``+experiment=joint``, codesign.protocol=codesign, the default): from the published camera
to a designed and a co-designed one, each stage compared with the published system at the same budget.

Stages, each in its own folder of the run directory; a stage whose metrics.json exists is not run again, and one
killed mid-training resumes from its checkpoint (the same command on the same hydra.run.dir continues), each only
with the settings it was made with (its stage_settings.json, compared before any work: codesign/train/
stage_settings.py):

  design/              (a) the mask moved into the codesign.design family (spline) and searched for the best
                           restorability under the LSR ceiling (search.*: +experiment=mask_search's search), the
                           ceiling being codesign.lsr_max less the gap between the samples and the certified peak
  restorer/            (b) the restorer trained on the designed mask, frozen, trainer.steps (from init.checkpoint when
                           given: a warm start; from scratch otherwise, and the log says so)
  published_restorer/      the same restorer, steps and seed on the published mask
  designed/                the designed mask frozen: restorer/ fine-tuned codesign.finetune_steps (the control arm)
  codesigned/          (c) joint: restorer/ fine-tuned the same steps with the mask trainable, its smooth LSR held at
                           the design's and its certified peak at or below codesign.lsr_max (the guard)
  published/           (d) published_restorer/ fine-tuned the same steps, the published mask frozen
Then summary.txt and metrics.json (codesign/train/protocol_summary.py): the masks' LSR (certified peak), MTF and
LSR / limit; per alpha_l the five systems (published + Wiener, published + network, designed + Wiener, designed +
network, co-designed); the gain of each stage with its 95 % interval over the scenes; systems.png.
With codesign.design=null there is no design stage: the configured mask (mask=halfring: the published half rings)
is the start, and the designed arm is its frozen arm.
"""
from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from codesign.config.runtime import check_seed, to_container
from codesign.design.merit import published_reference
from codesign.design.search_spec import SearchSpec
from codesign.errors import ConfigError
from codesign.experiments.specs import eval_settings, material_of, metrics_spec
from codesign.fab.laser_lines import lines_summary, run_lines
from codesign.io import files as io
from codesign.optics import OpticalSystem, OpticsSpec, build_mask
from codesign.optics.masks import FAMILIES, published_mask_config
from codesign.signals import Interrupted, TrainingInterrupted
from codesign.train import distributed
from codesign.train.data import build_simulated_data
from codesign.train.lsr_constraint import CodesignSpec
from codesign.train.memory import check_training_fits
from codesign.train.model_setup import build_model
from codesign.train.protocol_summary import protocol_summary, summary_record, systems_figure
from codesign.experiments.resume import initial_checkpoint, load_initial_weights
from codesign.train.spec import InitSpec, TrainerSpec
from codesign.train import stage_settings

log = logging.getLogger("codesign.main_job")

IMAGES_FILE = "images_compared.pt"  # a stage's first scenes restored at the compared laser strength
SHOWN_SCENES = 3
# the design stage's ceiling sits this far below codesign.lsr_max: the search bounds the samples (two focal grids),
# the certified peak between them lies up to 2.7 % above on the spline designs measured (docs/codesign.md Sec. 5)
PEAK_GAP = 0.03
DEFAULT_SHARE = 0.25  # codesign.lsr_max null with a design stage: a quarter of the published mask's certified peak
STAGES = ("design", "restorer", "published_restorer", "designed", "codesigned", "published")
# what a stage's recorded settings may differ in when a restart reuses it (stage_settings.py): the settings it never
# reads; the design stage trains no network, the restorer stages take trainer.steps, not codesign.finetune_steps
STAGE_UNREAD = {"design": ("trainer", "model", "init", "evaluate", "codesign.finetune_steps"),
                "restorer": ("codesign.finetune_steps",), "published_restorer": ("codesign.finetune_steps",)}
EVALUATED = ("published", "designed", "codesigned")


def save_images(path: Path, images: dict, method: str) -> Path:
    """The first SHOWN_SCENES scenes of an evaluation's kept images (truth, sensor image, Wiener, the restorer's
    output under "network"), written atomically."""
    keep = {"truth": "truth", "input": "input", "wiener": "wiener", method: "network"}
    out = {name: images[key][:SHOWN_SCENES].detach().cpu().clone() for key, name in keep.items() if key in images}
    return io.atomic_write_bytes(path, lambda f: torch.save(out, f))


def _stage_cfg(cfg: DictConfig, mask: dict, **changes) -> DictConfig:
    """``cfg`` with ``mask`` as its mask block and dotted ``changes``, as a single joint run of one stage."""
    out = OmegaConf.create(to_container(cfg))
    out.mask = mask
    # every stage holds its own start's smooth LSR (a frozen stage never moves; the joint stage adds its peak guard)
    base = {"codesign.protocol": "single", "codesign.compare_published": False, "codesign.lsr_max": "start",
            "codesign.peak_max": None}
    for key, value in {**base, **changes}.items():
        OmegaConf.update(out, key, value, force_add=True)
    return out


class Progress:
    """One line per stage with the training time left over every stage, at the seconds per step (stage overheads
    and evaluations included) of the stages done so far; inside a stage, its search or trainer logs its own ETA."""

    def __init__(self, steps: dict[str, int]):
        self.steps, self.t0 = dict(steps), time.perf_counter()
        self.total = 1 + sum(1 for n in steps.values() if n)  # the design stage and every training stage
        self.train_seconds, self.trained = 0.0, 0

    def start(self, k: int, stage: str, what: str) -> None:
        """Log the start of stage ``stage`` (number ``k``, ``what`` it does) with the training time left at the rate
        so far."""
        left = sum(n for s, n in self.steps.items() if STAGES.index(s) >= STAGES.index(stage))
        rate = self.train_seconds / self.trained if self.trained else None
        eta = f"about {left * rate / 60:.1f} min of training left" if rate else "time left: after the first stage"
        log.info("main job: stage %d/%d %s: %s (%.1f min so far; %s)", k, self.total, stage, what,
                 (time.perf_counter() - self.t0) / 60, eta)

    def done(self, stage: str, seconds: float) -> None:
        """Count a finished training stage's ``seconds`` and steps into the rate."""
        if self.steps.get(stage):
            self.train_seconds += seconds
            self.trained += self.steps[stage]


def run_protocol(cfg: DictConfig, run_dir: Path, device: torch.device, train) -> float:
    """The stages above; ``train(cfg, run_dir, device, evaluate)``: one single joint run (joint.run_single). Steps:
    build (every setting checked, the published mask's certified peak and the ceiling from it), design, train the
    restorer stages and the arms, report."""
    job = _build(cfg, run_dir, device)
    try:
        designed_cfg, design = _design_stage(job)
        _train_stages(job, designed_cfg, train)
    except Interrupted as stop:  # between stages, or in the design's search: say what is kept and how to go on
        note_finished_stages(stop, job.stages)
        raise
    return _report(job, design)


def note_finished_stages(stop: Interrupted, stages: dict) -> None:
    """Tell an interrupt of the main job (``stages``: name -> folder) which stages finished (their metrics.json):
    kept, and reused when the same command runs on this run folder; the interrupt line then lists them and the
    command that resumes (codesign/experiments/__init__.py interrupt_line). A stage's folder holds no file of the
    run folder itself, so the line listed only stage_seconds.json. A training stage's own interrupt
    (TrainingInterrupted: its checkpoint and the resume command) already says it."""
    if isinstance(stop, TrainingInterrupted):
        return
    done = []
    for folder in dict.fromkeys(stages.values()):  # a stage may serve as another (no design stage: one folder)
        if (folder / "metrics.json").is_file():
            done.append(f"{folder.name}/")
    stop.finished_stages = done


@dataclass
class _Job:
    """What the main job's stages share: its settings (the config with init.checkpoint resolved), the published
    system and the LSR ceiling, the stage folders, the progress line and the stages' wall seconds."""

    cfg: DictConfig
    run_dir: Path
    device: torch.device
    seed: int
    cs: CodesignSpec
    spec: TrainerSpec
    init: InitSpec
    asked: str | None  # init.checkpoint as given (auto before it was resolved)
    search: SearchSpec | None
    mask_cfg: dict
    published_cfg: dict
    system: OpticalSystem | None = None
    published: object = None
    published_peak: float = float("nan")
    lsr_max: float = float("nan")
    lsr_max_from: str = ""
    stages: dict = field(default_factory=dict)
    same: bool = False  # no design stage from the published mask: the published system is the designed one
    progress: Progress | None = None
    seconds_file: Path | None = None
    seconds: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)  # what each stage records as the settings that shaped it


def _build(cfg: DictConfig, run_dir: Path, device: torch.device) -> _Job:
    """Every setting checked before any work, the published mask's certified peak (the worst line's with
    codesign.lsr_over=wavelengths), the ceiling from it, the stage folders and the progress line."""
    settings = stage_settings.settings(to_container(cfg))  # as composed: init.checkpoint=auto as typed
    for stage in STAGES:  # a restart reuses a stage only with the settings it was made with: checked first
        stage_settings.check_stage(run_dir / stage, stage, settings, STAGE_UNREAD.get(stage, ()))
    job = _check(cfg, device)
    job.run_dir, job.settings = run_dir, settings
    cs = job.cs
    job.system = system = OpticalSystem(OpticsSpec.from_config(to_container(job.cfg.optics)), device=device)
    job.published = published = published_reference(job.mask_cfg, system)
    lines = run_lines(material_of(job.cfg), system, "codesign.lsr_over" if cs.lsr_over == "wavelengths" else None)
    with torch.no_grad():
        if cs.lsr_over == "wavelengths":  # the worst line's certified peak (the joint stage's guard: the design line's)
            phase = {"published": published.phase().detach()}
            job.published_peak = lines_summary(lines, phase, published.plate_cell_m)["published"]["lsr_worst"]
        else:
            job.published_peak = system.continuous_lsr(published.phase(), published.plate_cell_m)
    job.lsr_max, job.lsr_max_from = cs.lsr_max_value(lambda: job.published_peak, measure="certified peak",
                                                     default_share=DEFAULT_SHARE if cs.design is not None else 1.0)
    job.stages = {s: run_dir / s for s in STAGES}
    job.same = cs.design is None and job.mask_cfg == job.published_cfg
    pub_steps = (0, 0) if job.same else (job.spec.steps, cs.finetune_steps)
    job.progress = Progress({"restorer": job.spec.steps, "published_restorer": pub_steps[0],
                             "designed": cs.finetune_steps, "codesigned": cs.finetune_steps,
                             "published": pub_steps[1]})
    job.seconds_file = run_dir / "stage_seconds.json"  # each stage's wall seconds, kept across a resumed run
    job.seconds = json.loads(job.seconds_file.read_text()) if job.seconds_file.is_file() else {}
    return job


def _check(cfg: DictConfig, device: torch.device) -> _Job:
    """Every setting of the protocol checked before any work (init.checkpoint=auto resolved once: every stage then
    starts from the same weights); a warm start that does not fit, or a batch this machine cannot hold, refused
    now, not after the design stage."""
    seed = check_seed(cfg)
    cs = CodesignSpec.from_config(to_container(cfg.get("codesign")) or {})
    if distributed.current().enabled:  # its search and its folders are one process's
        raise ConfigError("codesign.protocol", cs.protocol, "runs in one process; under torchrun train one joint run "
                          "with codesign.protocol=single")
    spec = TrainerSpec.from_config(to_container(cfg.trainer))
    init = InitSpec.from_config(to_container(cfg.get("init")) or {})
    asked = init.checkpoint
    if init.checkpoint == "auto":
        cfg = OmegaConf.create(to_container(cfg))
        cfg.init.checkpoint = initial_checkpoint(init.checkpoint, cfg)
        init = InitSpec.from_config(to_container(cfg.init))
    eval_settings(cfg)
    mask_cfg = to_container(cfg.mask)
    search = _check_search(cfg) if cs.design is not None else None
    metrics_spec(cfg)
    published_cfg = published_mask_config(mask_cfg)
    probe, model = _stage_cfg(cfg, published_cfg), build_model(cfg)
    if init.checkpoint:
        load_initial_weights(model, init.checkpoint, cfg)
    check_training_fits(model, build_simulated_data(probe, device, seed), spec, device, "joint")
    return _Job(cfg, Path(), device, seed, cs, spec, init, asked, search, mask_cfg, published_cfg)


def _design_stage(job: _Job) -> tuple[dict, dict | None]:
    """Stage (a), or the configured mask as the start without one (codesign.design=null): (the designed mask's
    config, the search's metrics or None)."""
    cs = job.cs
    job.progress.start(1, "design", f"{cs.design or 'none'} family, certified-peak LSR <= {job.lsr_max:.4g} "
                                    f"({job.lsr_max_from})")
    t = time.perf_counter()
    if cs.design is not None:
        stage_settings.begin_stage(job.stages["design"], "design", job.settings)
        designed_cfg, design = _design(job.cfg, job.search, cs, job.lsr_max, job.stages["design"], job.device)
    else:
        designed_cfg, design = job.mask_cfg, None
        log.info("main job: no design stage (codesign.design=null): the configured %s mask is the start",
                 job.mask_cfg["kind"])
    _note_seconds(job.seconds_file, job.seconds, "design", time.perf_counter() - t)
    return designed_cfg, design


def _plan(job: _Job, designed_cfg: dict) -> list[tuple]:
    """The training stages in order: (stage, its mask config, its dotted changes, whether it is evaluated, the
    stage whose checkpoint it starts from)."""
    cs, spec, published_cfg = job.cs, job.spec, job.published_cfg
    frozen = {"codesign.mask_lr": 0.0}
    plan = [
        ("restorer", designed_cfg, {**frozen, "trainer.steps": spec.steps}, False, None),
        ("published_restorer", published_cfg, {**frozen, "trainer.steps": spec.steps}, False, None),
        ("designed", designed_cfg, {**frozen, "trainer.steps": cs.finetune_steps}, True, "restorer"),
        # (c) joint: the network already restores this mask, so the mask moves from the first step (no warm-up)
        ("codesigned", designed_cfg, {"trainer.steps": cs.finetune_steps, "codesign.warmup_fraction": 0.0,
                                      "codesign.peak_max": job.lsr_max}, True, "restorer"),
        # (d) the published system: the same restorer, the same steps, the published mask frozen
        ("published", published_cfg, {**frozen, "trainer.steps": cs.finetune_steps}, True, "published_restorer"),
    ]
    if job.same:  # no design stage from the published mask: its arms are the designed ones
        job.stages.update(published_restorer=job.stages["restorer"], published=job.stages["designed"])
        plan = [step for step in plan if not step[0].startswith("published")]
        log.info("main job: the start mask is the published one: its restorer and frozen arm serve as the published "
                 "system's")
    return plan


def _train_stages(job: _Job, designed_cfg: dict, train) -> None:
    """(b) the restorer on the designed mask and on the published one, from the same weights, then the arms (c, d);
    a stage whose metrics.json exists is not run again."""
    if job.init.checkpoint:
        log.info("main job: the restorer starts from %s (init.checkpoint)", job.init.checkpoint)
    else:
        log.info("main job: no pretrained restorer (init.checkpoint=%s): the restorer trains from scratch", job.asked)
    for k, (stage, mask, changes, evaluate, start) in enumerate(_plan(job, designed_cfg), start=2):
        folder = job.stages[stage]
        warm = {"init.checkpoint": str(job.stages[start] / "checkpoint.pt")} if start else {}
        job.progress.start(k, stage, f"{mask['kind']} mask, {changes['trainer.steps']} steps" +
                           (f", from {start}/" if start else ""))
        t = time.perf_counter()
        if not (folder / "metrics.json").is_file():
            stage_settings.begin_stage(folder, stage, job.settings)
            train(_stage_cfg(job.cfg, mask, **changes, **warm), folder, job.device, evaluate)
            _note_seconds(job.seconds_file, job.seconds, stage, time.perf_counter() - t)
            job.progress.done(stage, job.seconds[stage])
        else:
            log.info("main job: %s done before (%s)", stage, folder / "metrics.json")


def _report(job: _Job, design: dict | None) -> float:
    """summary.txt, metrics.json and systems.png of the evaluated stages; returns the co-designed system's PSNR
    after the gain/offset match at alpha_l = 1e6."""
    stages, run_dir = job.stages, job.run_dir
    metrics = {s: json.loads((stages[s] / "metrics.json").read_text()) for s in EVALUATED}
    record = summary_record(metrics, design, job.lsr_max, job.lsr_max_from, job.published_peak, job.seed,
                            {"trainer_steps": job.spec.steps, "finetune_steps": job.cs.finetune_steps}, job.seconds)
    record["checkpoint"] = str(stages["codesigned"] / "checkpoint.pt")
    shutil.copyfile(stages["codesigned"] / "learned_mask.json", run_dir / "learned_mask.json")
    images = {s: torch.load(stages[s] / IMAGES_FILE) for s in EVALUATED if (stages[s] / IMAGES_FILE).is_file()}
    if len(images) == len(EVALUATED):
        arrays = _mask_arrays(job.system, job.cfg, stages, job.published)
        io.save_figure(run_dir / "systems.png", systems_figure(arrays, images, record))
    text = protocol_summary(record)
    io.write_json(run_dir / "metrics.json", record)
    io.atomic_write_bytes(run_dir / "summary.txt", lambda f: f.write(text.encode() + b"\n"))
    print(text, flush=True)
    log.info("wrote %s", run_dir)
    final = record["systems"]["codesigned_network"]
    return final["laser_1e6"]["psnr_matched"] if "laser_1e6" in final else float("nan")


def _note_seconds(path: Path, seconds: dict, stage: str, value: float) -> None:
    """A finished stage's wall seconds into ``seconds`` and its file (a stage found done keeps its first value)."""
    seconds.setdefault(stage, value)
    io.write_json(path, seconds)


def _check_search(cfg: DictConfig) -> SearchSpec:
    """search.* of the design stage, checked before any work (its ceiling is the protocol's, set later)."""
    block = to_container(cfg.get("search")) or {}
    if block.get("lsr_ceiling") is not None:
        raise ConfigError("search.lsr_ceiling", block["lsr_ceiling"], "is set by the main job from codesign.lsr_max "
                          "(give codesign.lsr_max instead)")
    return SearchSpec.from_config({**block, "lsr_ceiling": 1.0})


def _design(cfg: DictConfig, search: SearchSpec, cs: CodesignSpec, lsr_max: float, folder: Path, device) -> tuple:
    """Stage (a): +experiment=mask_search's search of the codesign.design family under the ceiling (over the laser
    lines with codesign.lsr_over=wavelengths) in ``folder``, or its earlier result there; returns (the designed
    mask's config, the search's metrics)."""
    from codesign.experiments import mask_search  # nlopt and the search only where a design stage runs

    family = cs.design
    record, metrics = folder / "best_mask.json", folder / "metrics.json"
    ceiling = lsr_max * (1 - PEAK_GAP)
    if not (record.is_file() and metrics.is_file()):
        folder.mkdir(parents=True, exist_ok=True)
        mask = {**FAMILIES[family].Spec.defaults(), "kind": family}
        design_cfg = _stage_cfg(cfg, mask, **{"search.lsr_ceiling": ceiling, "search.lsr_over": cs.lsr_over})
        log.info("main job: design stage: %s search of the %s family, LSR ceiling %.4g (%.0f %% below the certified-"
                 "peak ceiling %.4g), %s evaluations", search.objective, family, ceiling, 100 * PEAK_GAP, lsr_max,
                 search.max_evals)
        mask_search.run(design_cfg, folder, device)
    else:
        log.info("main job: design stage done before (%s)", record)
    result = json.loads(metrics.read_text())
    # what must hold is the certified peak under codesign.lsr_max; the search's own ceiling sits PEAK_GAP below it,
    # so a design a hair above that ceiling (the search then says infeasible) can still be inside
    if result["lsr"] > lsr_max:
        log.warning("main job: the designed mask's certified peak LSR %.4g lies ABOVE codesign.lsr_max %.4g (the "
                    "search %s): the protocol goes on with it, and the joint stage's guard only lets it descend, but "
                    "it does not protect as asked (raise search.max_evals)", result["lsr"], lsr_max,
                    "ended feasible" if result.get("feasible") else "found no point under its ceiling")
    else:
        log.info("main job: the designed mask: certified peak LSR %.4g (<= %.4g), mtf_mean %.4g, restorability %.2f "
                 "dB (published %.2f)", result["lsr"], lsr_max, result["mtf_mean"], result["restorability"],
                 result["restorability_published"])
    mask = {**FAMILIES[family].Spec.defaults(), "kind": family, "init": str(record.resolve())}
    return mask, result


def _mask_arrays(system, cfg: DictConfig, stages: dict, published) -> dict:
    """Phase and PSF of the published, designed and co-designed masks (their records in the stage folders)."""
    out = {}
    aperture = system.grid.aperture.cpu().numpy()
    spec = system.spec
    for name, mask in (("published", published), ("designed", stages["designed"] / "learned_mask.json"),
                       ("co-designed", stages["codesigned"] / "learned_mask.json")):
        if isinstance(mask, Path):
            kind = json.loads(mask.read_text())["kind"]
            base = to_container(cfg.mask) if kind == cfg.mask.kind else FAMILIES[kind].Spec.defaults()
            mask = build_mask({**base, "kind": kind, "init": str(mask)}, system.grid,
                              spec.aperture_diameter_m).freeze()
        with torch.no_grad():
            phase = mask.phase()
            psf = system.psf(phase, mask.plate_cell_m) / system.uncoded_peak
        out[name] = {"phase": np.where(aperture > 0, phase.cpu().numpy(), np.nan), "psf": psf.cpu().numpy()}
    return out

