"""The trainer: one explicit loop for every restorer (codesign/models/restorer.py) and, with a MaskCodesign
component, for co-design. It owns every optimizer, the schedules, the EMA, logging, validation and checkpoints.

    while step < steps:
        update on one simulated batch        (codesign/train/gan_update.py: critics, then generators [+ mask])
        log the terms                        (every logging.log_every steps, the first and the last)
        validate                             (every trainer.val_every steps and at the end; rank 0)
        checkpoint                           (every trainer.checkpoint_every steps, at the end, on a stop signal)
        stop                                 (SIGINT / SIGTERM: checkpoint, then TrainingInterrupted; time budget)

Adam (betas of Sec. 6.2), weights and biases in separate groups (2e-4 / 4e-4), the Sec. 6.2 step schedule,
optional gradient clipping and generator EMA. No host-device synchronization inside a step: losses stay on the
device until a logging step reads them, so a GPU never waits for the Python side. Under torchrun the networks run
under DistributedDataParallel (codesign/train/distributed.py); only rank 0 validates, logs and writes checkpoints.
"""
from __future__ import annotations

import logging
import signal
import time
from pathlib import Path

import torch

from codesign.camera import field_of_view
from codesign.models import losses
from codesign.models.quality import psnr, ssim
from codesign.models.restorer import Restorer, TrainContext
from codesign.train import distributed
from codesign.train.evaluation import affine_match
from codesign.train.checkpoint import CHECKPOINT_NAME, rng_state, save_checkpoint, set_rng_state
from codesign.train.gan_update import GANUpdate
from codesign.train.optim import EMA, GuardedUpdate, adam, param_groups
from codesign.train.progress import LossRecord
from codesign.signals import TrainingInterrupted, stop_requests
from codesign.train.spec import TrainerSpec

log = logging.getLogger("codesign.train")


def as_float32(x):
    """Tensors (in lists, tuples, dicts) cast to float32: network outputs leave autocast in full precision."""
    if isinstance(x, torch.Tensor):
        return x.float() if x.is_floating_point() and x.dtype != torch.float64 else x
    if isinstance(x, (list, tuple)):
        return type(x)(as_float32(v) for v in x)
    if isinstance(x, dict):
        return {k: as_float32(v) for k, v in x.items()}
    return x


class Trainer(TrainContext):
    """Train ``model`` on simulated batches from ``data`` (a SimulatedData, or anything with train_batch(step),
    validation_batch(n), otf, image_size, state_dict(), load_state_dict()) under ``spec``; ``codesign``: a
    MaskCodesign (codesign/train/mask_codesign.py) when the camera's mask trains too; ``dist``: the torchrun
    context (SINGLE: one process). The trainer is the TrainContext of the restorer's losses: ``run`` (autocast,
    the training wrappers), ``critics`` (the critics' training wrappers) and ``gradient_penalty``."""

    def __init__(self, *, model: Restorer, data, spec: TrainerSpec, run_dir: Path, device: torch.device,
                 config: dict, seed: int, dist: distributed.DistContext = distributed.SINGLE, writer=None,
                 codesign=None):
        self.model, self.data, self.spec, self.codesign = model.to(device), data, spec, codesign
        self.run_dir, self.device, self.config, self.writer, self.dist = Path(run_dir), device, config, writer, dist
        model.prepare_training(device)
        gens, crits = model.generators(), model.critics()
        if spec.channels_last:
            model.to(memory_format=torch.channels_last)
        # the modules the training step runs: DDP wrappers sharing the model's parameters under torchrun, the
        # generators optionally compiled (all but those the restorer marks as not compilable)
        train_generators = [distributed.wrap(g, dist, device) for g in gens]
        if spec.compile:
            train_generators = [g if getattr(m, "no_compile", False) else torch.compile(g)
                                for g, m in zip(train_generators, gens)]
        super().__init__([distributed.wrap(c, dist, device) for c in crits])
        groups = param_groups(gens, spec.lr_weights, spec.lr_biases)
        factors = [spec.lr_factor] * len(groups)
        if codesign is not None:
            groups.append(codesign.param_group())
            factors.append(codesign.lr_factor(spec.lr_factor))
        self.opt_g = adam(groups, spec.betas, device)
        self.opt_d = adam(param_groups(crits, spec.lr_weights, spec.lr_biases), spec.betas, device) if crits \
            else None
        self.sched_g = torch.optim.lr_scheduler.LambdaLR(self.opt_g, factors)
        self.sched_d = torch.optim.lr_scheduler.LambdaLR(self.opt_d, spec.lr_factor) if crits else None
        self.ema = EMA(gens, spec.ema) if spec.ema else None
        self.guard = GuardedUpdate(device, spec.grad_clip, dist)
        self.update = GANUpdate(model=model, ctx=self, data=data, generators=train_generators, opt_g=self.opt_g,
                                opt_d=self.opt_d, guard=self.guard, ema=self.ema, critic_steps=spec.critic_steps,
                                codesign=codesign)
        self.gp_gen = torch.Generator(device=device).manual_seed(seed + 2)  # interpolation weights of the GP
        self.step = 0
        self.losses = LossRecord()
        self.last_val: dict = {}
        self.replica_diff = 0.0  # largest weight difference between ranks found by the last check
        # training steps of the same job that follow this training (a joint run's published comparison): the
        # progress line's ETA covers them too, at this training's rate
        self.steps_after = 0
        # what the final record needs from before a resume: the experiment's entries (e.g. the untrained network's
        # validation scores) and the training seconds so far; both travel in the checkpoint
        self.record: dict = {}
        self.seconds_before = 0.0
        self._fit_t0: float | None = None

    # ---- the loop -------------------------------------------------------------------------------------------------
    def fit(self, progress_every: int = 10) -> list[dict]:
        """Train to spec.steps (or the time budget). Loss terms are read (averaged over the ranks) only every
        ``progress_every`` steps, the first and the last: the console, TensorBoard and the returned [first, last]
        terms see those steps; in between the device runs ahead of the host."""
        spec = self.spec
        self._fit_t0 = t0 = time.perf_counter()
        start = self.step
        with stop_requests() as signals:
            while self.step < spec.steps:
                terms = self.train_step()
                asked, over = self._stop_requested(signals, t0)
                last = self.step == spec.steps or over
                scheduled = self._every(progress_every) or last or self.step == 1
                if scheduled or asked or self.step == start + 1:  # a resume's and a signal's extra lines: uncounted
                    self.log_terms(terms, t0, start, counted=scheduled)
                if self._every(spec.val_every) or last:
                    self.validate_all(images=last or self._every(spec.image_every))
                if self._every(spec.checkpoint_every) or last or asked:
                    path = self.save() if self.dist.is_main else None
                if asked:
                    raise TrainingInterrupted(signals[0] if signals else signal.SIGTERM, self.step, path)
                if over:
                    log.info("time budget of %.0f s reached at step %d/%d", spec.time_budget_s, self.step, spec.steps)
                    break
        if self.dist.is_main:
            self.losses.warn_if_diverged()
        # the training's seconds stop here: what follows (calibrate, evaluation) is not training time
        self.seconds_before, self._fit_t0 = self.train_seconds, None
        return [t for t in (self.losses.first, self.losses.last) if t]

    def train_step(self) -> dict:
        """One update (critics, then generators and mask) on the batch of this step; returns the loss terms as
        detached 0-dim tensors on the device (this rank's batch share)."""
        self.model.train()
        if self.codesign is not None:
            self.codesign.begin_step(self.codesign.active(self.step, self.spec.lr_factor))
        terms = self.update(self.data.train_batch(self.step))
        self.sched_g.step()
        if self.sched_d is not None and self.model.adversarial:  # critics without adversarial weight take no step
            self.sched_d.step()
        self.step += 1
        return terms

    def _every(self, n: int | None) -> bool:
        return bool(n) and self.step % n == 0

    def _stop_requested(self, signals: list, t0: float) -> tuple[bool, bool]:
        """(a stop signal arrived, the time budget is spent), agreed by every rank (rank 0's decide)."""
        budget = self.spec.time_budget_s
        over = budget is not None and time.perf_counter() - t0 >= budget
        asked = bool(signals)
        if self.dist.enabled:
            if budget is not None:
                over = distributed.broadcast_flag(over, self.dist)
            asked = distributed.broadcast_flag(asked, self.dist)
        return asked, over

    # ---- what the restorer's losses ask of the trainer (TrainContext) ------------------------------------------
    def gradient_penalty(self, critic, real, fake, cond=None):
        """The critic's gradient penalty between ``real`` and ``fake`` (WGAN-GP), its interpolation weights drawn for
        the whole global batch so that any number of ranks draws the same."""
        # the interpolation weights of the whole global batch, then this rank's share: the same draws whatever the
        # number of processes
        b = real.shape[0]
        eps = torch.rand((b * self.dist.world,), generator=self.gp_gen, device=real.device, dtype=real.dtype)
        eps = eps[self.dist.shard(b * self.dist.world)]
        return losses.gradient_penalty(lambda x: self.run(critic, x), real, fake, cond=cond, eps=eps)

    def autocast(self):
        """bfloat16 autocast of the networks' forward passes when trainer.amp = bf16 (else a no-op context)."""
        return torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.spec.amp == "bf16")

    def run(self, module, *args):
        """``module(*args)`` under the trainer's autocast, the outputs back in float32 for the losses."""
        if self.spec.channels_last:
            args = tuple(a.contiguous(memory_format=torch.channels_last) if isinstance(a, torch.Tensor)
                         and a.dim() == 4 else a for a in args)
        with self.autocast():
            return as_float32(module(*args))

    # ---- logging ------------------------------------------------------------------------------------------------
    @property
    def skipped(self) -> int:
        """Updates skipped so far (reads the device counter: a host sync)."""
        return self.guard.skipped

    @property
    def rollbacks(self) -> int:
        """Updates undone because they left a weight non-finite (reads the device counter: a host sync)."""
        return self.guard.undone

    def divergence(self) -> dict:
        """Whether the training diverged, and by how much (LossRecord.divergence)."""
        return self.losses.divergence()

    @property
    def train_seconds(self) -> float:
        """Seconds spent in fit() over the whole run, before and after any resume."""
        return self.seconds_before + (time.perf_counter() - self._fit_t0 if self._fit_t0 is not None else 0.0)

    def log_terms(self, terms: dict, t0: float, start: int, counted: bool = True) -> None:
        """Read this step's terms (global-batch means), record and log them and the guards' reports; the progress
        line. ``counted``: the terms update the lowest logged values (divergence)."""
        if self.codesign is not None:
            self.codesign.check_replicas(self.replica_check)
        values = distributed.all_mean(terms, self.dist)
        values["step"] = self.step
        self.losses.add(values, counted)
        self.guard.report(self.step)
        if self.dist.is_main and self.writer is not None:
            self._log_scalars(values)
        rate = (time.perf_counter() - t0) / (self.step - start)
        shown = "".join(f"  {k} {values[k]:.4g}" for k in ("rec1", "rec2") if k in values)
        critic = f"  D {values['critic_total']:.4g}" if "critic_total" in values else ""
        mask = self.codesign.progress() if self.codesign is not None else ""
        log.info("step %d/%d  G %.4g%s%s%s  %.2f s/step  ETA %.0f s", self.step, self.spec.steps,
                 values["generator_total"], shown, critic, mask, rate,
                 rate * (self.spec.steps - self.step + self.steps_after))

    def _log_scalars(self, terms: dict) -> None:
        scalars = {f"loss/{k}": v for k, v in terms.items() if k != "step"}
        scalars.update(self.model.scalars())
        for opt, name in ((self.opt_g, "generator"), (self.opt_d, "critic")):
            for g in (opt.param_groups if opt is not None else ()):
                scalars[f"lr/{name}_{g['name']}"] = g["lr"]
        if self.codesign is not None:
            scalars.update(self.codesign.scalars())
        for k, v in scalars.items():
            self.writer.add_scalar(k, v, self.step)

    # ---- validation and replicas --------------------------------------------------------------------------------
    def validate_all(self, images: bool) -> None:
        """The validation of a logging step: the replicas checked (every rank), then rank 0 validates."""
        self.check_replicas()
        if self.dist.is_main:
            self.validate(images)

    def restoring_modules(self) -> list:
        """The generators used for evaluation: the EMA copies when EMA is on."""
        return self.ema.shadow if self.ema is not None else self.model.generators()

    @torch.no_grad()
    def validate(self, images: bool) -> dict:
        """PSNR / SSIM of the restoring modules on the fixed validation batch (field of view), logged to
        TensorBoard with, when ``images``, a panel of inputs, outputs and targets; the mask's figures of merit in
        co-design."""
        batch = self.data.validation_batch(self.spec.val_size)  # through the current mask (the data caches the rest)
        out = self.model.restore(batch["sensor"], self.data.otf, self.restoring_modules())
        n = self.data.image_size
        crop = lambda x: field_of_view(x, n).clamp(0, 1)  # noqa: E731
        b, t = crop(out["restored"]), crop(batch["scene"])
        metrics = {"val/psnr": float(psnr(b, t).mean()), "val/ssim": float(ssim(b, t).mean()),
                   # after the per-image gain and offset (the scene's level is not in the image: held to the
                   # exposure, a restorer's plain PSNR says little of its progress)
                   "val/psnr_matched": float(psnr(affine_match(field_of_view(out["restored"], n), t), t).mean())}
        if "i_b" in out:  # a restorer with a pre-restored irradiance (the SGAN's G1)
            metrics["val/psnr_i_b"] = float(psnr(crop(out["i_b"]), crop(batch["irradiance"])).mean())
        if self.writer is not None:
            for k, v in metrics.items():
                self.writer.add_scalar(k, v, self.step)
            if images:
                k = min(4, batch["sensor"].shape[0])
                panel = {"sensor_input": batch["sensor"], "pre_restored_i_b": out.get("i_b"),
                         "restored_b": out["restored"], "ground_truth_b": batch["scene"],
                         "target_i_b": batch["irradiance"] if "i_b" in out else None}
                for name, img in panel.items():
                    if img is not None:
                        self.writer.add_images(f"images/{name}", img[:k].clamp(0, 1).cpu(), self.step)
            self.writer.flush()
        if self.codesign is not None:
            metrics.update(self.codesign.validate(self.writer, self.step, images))
        self.last_val = metrics
        return metrics

    def check_replicas(self) -> float:
        """Under torchrun: the largest difference between a rank's parameters (and mask) and rank 0's (0.0:
        identical, as DDP keeps them; a difference is logged, repaired from rank 0 and reported in metrics.json)."""
        if not self.dist.enabled:
            return 0.0
        diff = self.replica_check(self.replicated_parameters(), "parameters", "distributed/max_parameter_difference")
        self.replica_diff = max(self.replica_diff, diff)
        return diff

    def replicated_parameters(self) -> list[torch.Tensor]:
        """Parameters that must be identical on every rank: the networks' and, in co-design, the mask's."""
        params = [p for m in self.model.generators() + self.model.critics() for p in m.parameters()]
        return params + (self.codesign.params if self.codesign is not None else [])

    def replica_check(self, params: list, what: str, tag: str) -> float:
        """Largest difference of ``params`` to rank 0's (repaired from rank 0 when non-zero), warned about and
        logged to TensorBoard as ``tag``. A collective: every rank calls it at the same step."""
        diff = distributed.replica_divergence(params, self.dist)
        if diff > 0:
            log.warning("step %d: %s differed between ranks by up to %.3g: reset to rank 0's", self.step, what, diff)
        if self.writer is not None:
            self.writer.add_scalar(tag, diff, self.step)
        return diff

    # ---- checkpoints ----------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """The checkpoint: model, optimizers, schedules, step, EMA, every random state, the data's position, the
        config and the record."""
        return {
            "model": self.model.state_dict(), "opt_g": self.opt_g.state_dict(), "step": self.step,
            "opt_d": self.opt_d.state_dict() if self.opt_d is not None else None,
            "sched_g": self.sched_g.state_dict(),
            "sched_d": self.sched_d.state_dict() if self.sched_d is not None else None,
            "skipped": self.skipped, "ema": self.ema.state_dict() if self.ema else None,
            "rng": {**rng_state(), "gp": self.gp_gen.get_state(), "gp_device": self.gp_gen.device.type,
                    "data": self.data.state_dict()},
            "config": self.config, "model_spec": dict(vars(self.model.spec)), "world_size": self.dist.world,
            "versions": {"torch": str(torch.__version__)},
            "record": {**self.record, **self.losses.state_dict(), "last_val": self.last_val},
            "seconds": self.train_seconds,
            **(self.codesign.state_dict() if self.codesign is not None else {}),
        }

    def calibrate(self) -> dict:
        """The restorer's fitted parts (Restorer.calibrate, e.g. model.level_head) on this training's data, into the
        model and the restoring modules; then (rank 0) the validation scores taken again and the checkpoint written
        again with them, so that its final scores are those of the network it holds. What metrics.json records ({}
        when the restorer fits nothing). Every rank fits the same (the same batch, the same weights)."""
        facts = self.model.calibrate(self.restoring_modules(), self.data, crops=self.spec.calibrate_crops)
        if facts:
            self.record.update(facts)
            if self.dist.is_main:
                self.validate(images=False)
                self.save()
        return facts

    def save(self, path: Path | None = None) -> Path:
        """Write the checkpoint to ``path`` (default: the run directory's checkpoint.pt), atomically; returns its
        path."""
        return save_checkpoint(path or self.run_dir / CHECKPOINT_NAME, self.state_dict())

    def load_state_dict(self, state: dict) -> None:
        """Resume from a ``state_dict``: model, optimizers, schedules, step, record, EMA and random states."""
        self.model.load_state_dict(state["model"])
        self.opt_g.load_state_dict(state["opt_g"])
        self.sched_g.load_state_dict(state["sched_g"])
        if self.opt_d is not None:
            self.opt_d.load_state_dict(state["opt_d"])
            self.sched_d.load_state_dict(state["sched_d"])
        self.step = int(state["step"])
        record = dict(state.get("record") or {})  # absent in checkpoints written before it existed
        self.losses.load_state_dict(record)
        self.last_val = dict(record.get("last_val", {}) or {})
        self.record = {k: v for k, v in record.items() if k not in ("first_terms", "lowest_terms", "last_val")}
        self.seconds_before = float(state.get("seconds", 0.0))
        self.guard.load(int(state.get("skipped", 0)))
        if self.ema is not None:
            if state.get("ema"):
                self.ema.load_state_dict(state["ema"])
            else:  # EMA switched on at resume: start the average from the loaded weights, not the random init
                self.ema.load_state_dict([g.state_dict() for g in self.model.generators()])
        rng = state["rng"]
        set_rng_state(rng)
        if rng.get("gp_device", "cpu") == self.gp_gen.device.type:
            self.gp_gen.set_state(rng["gp"])
        else:  # CPU and CUDA generators have different states: the next steps differ from the original run's
            log.warning("checkpoint from a %s run resumed on %s: gradient-penalty draws re-seeded",
                        rng.get("gp_device", "cpu"), self.gp_gen.device.type)
            self.gp_gen.manual_seed(int(self.step) + 2)
        self.data.load_state_dict(rng["data"])
        if self.codesign is not None:
            self.codesign.load_state_dict(state)
