"""The restoration trainer: owns every optimizer, the GAN step order, schedules, EMA, logging and checkpoints, for
any restorer (codesign/models/restorer.py: the SGAN, or a plug-in).

Step order (one generator update), after one forward pass of the generators:
  1. critics (trainer.critic_steps times, when the restorer is adversarial) on that pass's outputs detached,
     with the restorer's critic terms (for the SGAN: WGAN terms and gradient penalty of D1 and both D2 scales).
  2. generators, reusing the pass (they have not changed): critics frozen (requires_grad False), with the
     restorer's generator terms (for the SGAN: adversarial + Charbonnier L1 + MDF + VGG + FFT).
Adam (betas of Sec. 6.2), weights and biases in separate groups (2e-4 / 4e-4), the Sec. 6.2 step schedule,
optional gradient clipping and generator EMA. A non-finite loss or gradient skips the update (counted, and
reported at the next logging step); an update that leaves a weight non-finite all the same (finite gradients and a
huge step) is undone: weights and Adam moments back to their values before it (counted as a rollback).

No host-device synchronization inside a step: losses stay on the device until a logging step reads them, and a
skipped update is decided on the device (Adam's fused kernel takes a ``found_inf`` flag, the protocol of
torch.amp.GradScaler), so a GPU never waits for the Python side. Under torchrun the networks run under
DistributedDataParallel (codesign/train/distributed.py); only rank 0 validates, logs and writes checkpoints.
"""
from __future__ import annotations

import copy
import logging
import math
import signal
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import torch
import torch.nn as nn

from codesign.camera import field_of_view
from codesign.models import losses
from codesign.models.quality import psnr, ssim
from codesign.models.restorer import Restorer, TrainContext
from codesign.train import distributed
from codesign.train.checkpoint import (
    CHECKPOINT_NAME,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from codesign.train.spec import TrainerSpec

log = logging.getLogger("codesign.train")

# A reconstruction term ending this many times above its lowest logged value marks the run as diverged (a sound run
# ends within a few times its lowest; learning rates 5000x the default end 4.8e4x above it after 16 smoke steps).
DIVERGED_FACTOR = 100.0


def reconstruction_terms(terms: dict) -> list[str]:
    """The reconstruction loss terms (rec1, rec2, ...: every restorer's fit to the target) among logged ``terms``;
    the adversarial and total terms change sign and scale by design, so divergence is judged on these."""
    return [k for k in terms if k.startswith("rec")]


class TrainingInterrupted(Exception):
    """SIGINT or SIGTERM arrived during training: the step in progress finished, a checkpoint was written (rank 0)
    and training stopped. ``exit_code``: 128 + the signal's number (130 for SIGINT, 143 for SIGTERM)."""

    def __init__(self, signum: int, step: int, checkpoint: Path | None):
        self.signum, self.step, self.checkpoint = signum, step, checkpoint
        self.exit_code = 128 + signum
        super().__init__(f"{signal.Signals(signum).name} at step {step}")


@contextmanager
def stop_requests():
    """SIGINT (Ctrl-C) and SIGTERM (what SLURM sends before a time limit) append their number to the yielded list
    instead of stopping the process: the training loop reads it at the next step boundary. A second signal stops
    at once, as before. Outside the main thread (signals cannot be caught there) the list stays empty."""
    got: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield got
        return
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

    def request(signum, frame):
        if got:  # asked twice: stop now
            signal.signal(signum, old[signum] if callable(old[signum]) else signal.SIG_DFL)
            raise KeyboardInterrupt
        got.append(signum)
        log.warning("%s: stopping after this step (checkpoint, then exit; again to stop at once)",
                    signal.Signals(signum).name)

    for s in old:
        signal.signal(s, request)
    try:
        yield got
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)


def init_weights(module: nn.Module) -> None:
    """Orthogonal weights and zero biases (Sec. 6.2); layers marked ``zero_init`` (attention output projections,
    generator output layers, skips) stay zero; norms stay at identity."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
            if getattr(m, "zero_init", False):
                continue
            nn.init.orthogonal_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)


def param_groups(modules: list[nn.Module], lr_w: float, lr_b: float) -> list[dict]:
    weights, biases = [], []
    for mod in modules:
        for name, p in mod.named_parameters():
            (biases if name.endswith("bias") else weights).append(p)
    return [{"params": weights, "lr": lr_w, "name": "weights"}, {"params": biases, "lr": lr_b, "name": "biases"}]


class EMA:
    """Exponential moving average of the generators' parameters and buffers."""

    def __init__(self, modules: list[nn.Module], decay: float):
        self.decay = decay
        self.shadow = [copy.deepcopy(m).requires_grad_(False) for m in modules]

    @torch.no_grad()
    def update(self, modules: list[nn.Module], applied: torch.Tensor | None = None) -> None:
        """Move the average toward ``modules``; ``applied`` (0-dim bool on the device): whether the update being
        averaged happened (a skipped one leaves the average exactly as it was, without a host sync)."""
        weight = 1.0 - self.decay
        for s, m in zip(self.shadow, modules):
            for ps, p in zip(s.parameters(), m.parameters()):
                ps.lerp_(p, weight if applied is None else applied.to(ps.dtype) * weight)
            for bs, b in zip(s.buffers(), m.buffers()):
                bs.copy_(b)

    def state_dict(self) -> list[dict]:
        return [s.state_dict() for s in self.shadow]

    def load_state_dict(self, states: list[dict]) -> None:
        for s, st in zip(self.shadow, states):
            s.load_state_dict(st)


def set_requires_grad(modules, flag: bool) -> None:
    for m in modules:
        for p in (m.parameters() if isinstance(m, nn.Module) else m):
            p.requires_grad_(flag)


def as_float32(x):
    """Tensors (in lists, tuples, dicts) cast to float32: network outputs leave autocast in full precision."""
    if isinstance(x, torch.Tensor):
        return x.float() if x.is_floating_point() and x.dtype != torch.float64 else x
    if isinstance(x, (list, tuple)):
        return type(x)(as_float32(v) for v in x)
    if isinstance(x, dict):
        return {k: as_float32(v) for k, v in x.items()}
    return x


def snapshot_optimizer(opt: torch.optim.Optimizer) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(tensor, copy) of every parameter of ``opt`` and of its existing state tensors (Adam's moments and step)
    before a step; states the step is about to create (the first step) have no entry (restore_if_not_finite sets
    them back to 0, their value before)."""
    out = []
    for group in opt.param_groups:
        for p in group["params"]:
            out.append((p, p.detach().clone()))
            for v in opt.state.get(p, {}).values():
                if torch.is_tensor(v):
                    out.append((v, v.clone()))
    return out


@torch.no_grad()
def restore_if_not_finite(opt: torch.optim.Optimizer, before: list) -> torch.Tensor:
    """Undo the step just taken if it left any parameter non-finite: parameters and state tensors back to
    ``before`` (states created by the step back to 0, Adam's initial state). Decided on the device, without a
    host sync (the step's other checks read no device value either, tests/train/test_train_options.py). Returns
    the 0-dim bool: undone."""
    params = [p for group in opt.param_groups for p in group["params"]]
    if not params:
        return torch.zeros((), dtype=torch.bool)
    bad = torch.stack([~torch.isfinite(p).all() for p in params]).any()
    known = {id(t) for t, _ in before}
    for t, old in before:
        t.copy_(torch.where(bad, old, t))
    for p in params:
        for v in opt.state.get(p, {}).values():
            if torch.is_tensor(v) and id(v) not in known:
                v.copy_(torch.where(bad, torch.zeros_like(v), v))
    return bad


def adam(groups: list[dict], betas, device: torch.device) -> torch.optim.Adam:
    """Adam with the fused kernel: one launch per step, and it honours the ``found_inf`` flag of a skipped update."""
    return torch.optim.Adam(groups, betas=betas, fused=device.type in ("cuda", "cpu"))


class RestorationTrainer(TrainContext):
    """Train a restorer on simulated batches from ``data`` (a SimulatedData or anything with train_batch(step),
    validation_batch(n), otf, image_size, state_dict(), load_state_dict()). ``dist``: the torchrun context
    (SINGLE: one process). The trainer is the TrainContext of the restorer's losses: ``run`` (autocast, the
    training wrappers), ``critics`` (the critics' training wrappers) and ``gradient_penalty``."""

    def __init__(self, model: Restorer, data, spec: TrainerSpec, run_dir: Path, device: torch.device,
                 config: dict, writer=None, seed: int = 0, dist: distributed.DistContext = distributed.SINGLE):
        self.model, self.data, self.spec = model.to(device), data, spec
        self.run_dir, self.device, self.config, self.writer = Path(run_dir), device, config, writer
        self.dist = dist
        model.prepare_training(device)
        gens, crits = model.generators(), model.critics()
        if spec.channels_last:
            model.to(memory_format=torch.channels_last)
        # the modules the training step runs: DDP wrappers sharing the model's parameters under torchrun, the
        # generators optionally compiled (all but those the restorer marks as not compilable)
        self.train_generators = [distributed.wrap(g, dist, device) for g in gens]
        if spec.compile:
            self.train_generators = [g if getattr(m, "no_compile", False) else torch.compile(g)
                                     for g, m in zip(self.train_generators, gens)]
        super().__init__([distributed.wrap(c, dist, device) for c in crits])
        self.opt_g = adam(param_groups(gens, spec.lr_weights, spec.lr_biases) + self.extra_generator_groups(),
                          spec.betas, device)
        self.opt_d = adam(param_groups(crits, spec.lr_weights, spec.lr_biases), spec.betas, device) if crits \
            else None
        self.sched_g = torch.optim.lr_scheduler.LambdaLR(self.opt_g, self.generator_lr_factors())
        self.sched_d = torch.optim.lr_scheduler.LambdaLR(self.opt_d, spec.lr_factor) if crits else None
        self.ema = EMA(gens, spec.ema) if spec.ema else None
        self.gp_gen = torch.Generator(device=device).manual_seed(seed + 2)  # interpolation weights of the GP
        self.step = 0
        self._skips = torch.zeros(2, dtype=torch.long, device=device)  # updates skipped: non-finite loss, gradient
        self._skips_reported = [0, 0]
        self._rollbacks = torch.zeros((), dtype=torch.long, device=device)  # updates undone: non-finite weights
        self._rollbacks_reported = 0
        self.replica_diff = 0.0  # largest weight difference between ranks found by the last check
        # training steps of the same job that follow this training (a joint run's published comparison): the
        # progress line's ETA covers them too, at this training's rate
        self.steps_after = 0
        self.first_terms: dict = {}  # loss terms of the run's first logged step (kept across resumes)
        self.last_terms: dict = {}
        self.lowest_terms: dict = {}  # lowest logged value of each reconstruction term (kept across resumes)
        self.last_val: dict = {}
        # what the final record needs from before a resume: the experiment's entries (e.g. the untrained network's
        # validation scores) and the training seconds so far; both travel in the checkpoint
        self.record: dict = {}
        self.seconds_before = 0.0
        self._fit_t0: float | None = None

    # ---- losses ---------------------------------------------------------------------------------------------
    @property
    def skipped(self) -> int:
        """Updates skipped so far (reads the device counter: a host sync)."""
        return int(self._skips.sum())

    def gradient_penalty(self, critic, real, fake, cond=None):
        # the interpolation weights of the whole global batch, then this rank's share: the same draws whatever
        # the number of processes
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

    def critic_step(self, batch: dict, out: dict | None = None) -> dict:
        """One critic update. ``out``: the generators' outputs for this batch (detached by the restorer);
        None = compute them without gradient."""
        if out is None:
            with torch.no_grad():
                out = self.generate(batch)
        terms = self.model.critic_losses(batch, out, self)
        terms["critic_skipped"] = (~self._apply(self.opt_d, terms["critic_total"], self.model.critics())).float()
        return terms

    def generator_losses(self, batch: dict, out: dict) -> dict:
        """The restorer's generator terms (subclasses add theirs, e.g. the LSR penalty of co-design)."""
        return self.model.generator_losses(batch, out, self)

    def generator_step(self, batch: dict, out: dict | None = None) -> dict:
        """One generator update with every critic frozen. ``out``: this batch's generator outputs with their
        graph (the generators have not changed since they were computed); None = compute. The frozen critics
        run as plain modules (no DDP: they take no update here)."""
        m = self.model
        crits = m.critics()
        set_requires_grad(crits, False)  # critics frozen: no gradient accumulates in them
        try:
            if out is None:
                out = self.generate(batch)
            terms = self.generator_losses(batch, out)
        finally:
            set_requires_grad(crits, True)
        applied = self._apply(self.opt_g, terms["generator_total"], m.generators())
        terms["generator_skipped"] = (~applied).float()
        if self.ema is not None:
            self.ema.update(m.generators(), applied)
        return terms

    def generate(self, batch: dict) -> dict:
        """The generators' outputs for ``batch`` through the training wrappers, with their graph."""
        return self.run(lambda s, otf: self.model.forward_with(self.train_generators, s, otf),
                        batch["sensor"], batch.get("otf", self.data.otf))

    def extra_generator_groups(self) -> list[dict]:
        """Parameter groups the generator optimizer steps beside the networks' (a trainable mask's)."""
        return []

    def generator_lr_factors(self) -> list:
        """One learning-rate factor function of the step per generator parameter group."""
        return [self.spec.lr_factor] * len(self.opt_g.param_groups)

    def extra_parameters(self, opt) -> list:
        """Parameters that ``opt`` updates beyond the modules' (a trainable mask): gradient-checked, not clipped."""
        return []

    def after_update(self, opt, applied: torch.Tensor) -> None:
        """Called right after ``opt.step()``; ``applied``: 0-dim bool on the device, False when the update was
        skipped (a trainable mask projects itself here)."""

    def _apply(self, opt, loss: torch.Tensor, modules) -> torch.Tensor:
        """Backward, clip, step; returns a 0-dim bool on the device, False when the loss or a gradient is not
        finite, in which case the fused Adam step leaves parameters and moments exactly as they were.

        The backward always runs, even for a non-finite loss: under DDP every rank must take part in the
        gradient all-reduce, and the ranks then agree on the skip (any rank's non-finite loss skips them all).
        """
        opt.zero_grad(set_to_none=True)
        loss.backward()
        params = [p for mod in modules for p in mod.parameters() if p.grad is not None]
        max_norm = self.spec.grad_clip if self.spec.grad_clip else math.inf
        norm = torch.nn.utils.clip_grad_norm_(params, max_norm, foreach=True)
        bad_loss = distributed.any_rank(~torch.isfinite(loss.detach()), self.dist)
        bad_grad = ~torch.isfinite(norm)
        for p in self.extra_parameters(opt):
            if p.grad is not None:
                bad_grad = bad_grad | ~torch.isfinite(p.grad).all()
        skip = bad_loss | bad_grad
        self._skips += torch.stack([bad_loss, bad_grad & ~bad_loss]).long()
        before = snapshot_optimizer(opt)
        if opt.defaults.get("fused"):
            opt.found_inf = skip.to(torch.float32)  # torch.optim's fused-step protocol (torch.amp.GradScaler's)
            try:
                opt.step()
            finally:
                del opt.found_inf
        elif not bool(skip):  # a device without the fused kernel decides on the host
            opt.step()
        undone = restore_if_not_finite(opt, before)
        self._rollbacks += undone.long()
        applied = ~skip & ~undone
        self.after_update(opt, applied)
        return applied

    def report_skips(self) -> None:
        """Warn about updates skipped since the last report (reads the device counters: call at logging steps)."""
        counts = self._skips.tolist()
        new = [c - r for c, r in zip(counts, self._skips_reported)]
        if any(new):
            log.warning("step %d: %d update(s) skipped since the last report (%d non-finite loss, %d non-finite "
                        "gradient)", self.step, sum(new), new[0], new[1])
        self._skips_reported = counts
        rollbacks = int(self._rollbacks)
        if rollbacks > self._rollbacks_reported:
            log.warning("step %d: %d update(s) left non-finite weights and were undone since the last report "
                        "(weights and Adam moments restored)", self.step, rollbacks - self._rollbacks_reported)
        self._rollbacks_reported = rollbacks

    @property
    def rollbacks(self) -> int:
        """Updates undone because they left a weight non-finite (reads the device counter: a host sync)."""
        return int(self._rollbacks)

    # ---- loop -----------------------------------------------------------------------------------------------
    def train_step(self) -> dict:
        """Critic update(s), then the generator update, on one simulated batch. The generators run once: the
        critic steps see their outputs detached, the generator step reuses them with their graph. Returns the
        loss terms as detached 0-dim tensors on the device (this rank's batch share)."""
        self.model.train()
        batch = self.data.train_batch(self.step)
        out = self.generate(batch)
        terms = {}
        if self.opt_d is not None and self.model.adversarial:
            for _ in range(self.spec.critic_steps):
                terms.update(self.critic_step(batch, out))
        terms.update(self.generator_step(batch, out))
        self.sched_g.step()
        if self.sched_d is not None:
            self.sched_d.step()
        self.step += 1
        return {k: v.detach() for k, v in terms.items()}

    def fit(self, progress_every: int = 10) -> list[dict]:
        """Train to spec.steps (or the time budget). Loss terms are read (averaged over the ranks) only every
        ``progress_every`` steps, the first and the last: the console, TensorBoard and the returned
        [first, last] terms see those steps; in between the device runs ahead of the host."""
        spec = self.spec
        t0, start = time.perf_counter(), self.step
        self._fit_t0 = t0
        with stop_requests() as stop:
            while self.step < spec.steps:
                terms = self.train_step()
                over = spec.time_budget_s is not None and time.perf_counter() - t0 >= spec.time_budget_s
                if self.dist.enabled and spec.time_budget_s is not None:  # all ranks stop together: rank 0's clock
                    over = distributed.broadcast_flag(over, self.dist)
                asked = bool(stop)
                if self.dist.enabled:  # a signal stops every rank at the same step (rank 0's decides)
                    asked = distributed.broadcast_flag(asked, self.dist)
                last = self.step == spec.steps or over
                scheduled = self.step % progress_every == 0 or last or self.step == 1
                if scheduled or asked or self.step == start + 1:
                    # the extra lines (the first step after a resume, a stop signal) are not counted in the lowest
                    # terms: a resumed run records the divergence figures of an uninterrupted one
                    self._log_step(terms, t0, start, counted=scheduled)
                if spec.val_every and (self.step % spec.val_every == 0) or last:
                    self.check_replicas()
                    if self.dist.is_main:
                        self.validate(images=last or bool(spec.image_every and self.step % spec.image_every == 0))
                if (spec.checkpoint_every and self.step % spec.checkpoint_every == 0 or last or asked) \
                        and self.dist.is_main:
                    path = self.save()
                if asked:
                    raise TrainingInterrupted(stop[0] if stop else signal.SIGTERM, self.step,
                                              path if self.dist.is_main else None)
                if over:
                    log.info("time budget of %.0f s reached at step %d/%d", spec.time_budget_s, self.step,
                             spec.steps)
                    break
        self.warn_if_diverged()
        return [t for t in (self.first_terms, self.last_terms) if t]

    def divergence(self) -> dict:
        """``diverged`` (1 or 0): a reconstruction term ended non-finite or more than DIVERGED_FACTOR times above
        its lowest logged value; ``loss_growth``: the largest last / lowest ratio; ``loss_growth_term``."""
        growth, worst = 1.0, None
        for k in reconstruction_terms(self.last_terms):
            last, low = self.last_terms[k], self.lowest_terms.get(k)
            ratio = math.inf if not math.isfinite(last) else last / low if low else 1.0
            if ratio > growth:
                growth, worst = ratio, k
        return {"diverged": int(growth > DIVERGED_FACTOR), "loss_growth": growth, "loss_growth_term": worst}

    def warn_if_diverged(self) -> None:
        d = self.divergence()
        if d["diverged"] and self.dist.is_main:
            k = d["loss_growth_term"]
            log.warning("training DIVERGED: the reconstruction term %s ended at %.4g, %.3gx its lowest logged value "
                        "%.4g; the results are not a trained network's (lower trainer.lr_weights / "
                        "trainer.lr_biases; metrics.json: diverged = 1)", k, self.last_terms[k], d["loss_growth"],
                        self.lowest_terms.get(k, math.nan))

    @property
    def train_seconds(self) -> float:
        """Seconds spent in fit() over the whole run, before and after any resume."""
        return self.seconds_before + (time.perf_counter() - self._fit_t0 if self._fit_t0 is not None else 0.0)

    def _log_step(self, terms: dict, t0: float, start: int, counted: bool = True) -> None:
        """Read this step's terms (global-batch means), log them and the skips; the progress line; ``counted``: the
        terms update the lowest logged values (divergence)."""
        values = distributed.all_mean(terms, self.dist)
        values["step"] = self.step
        self.first_terms = self.first_terms or values
        self.last_terms = values
        for k in reconstruction_terms(values) if counted else ():
            if math.isfinite(values[k]):
                self.lowest_terms[k] = min(self.lowest_terms.get(k, math.inf), values[k])
        self.report_skips()
        if self.dist.is_main:
            self._log_scalars(values)
        rate = (time.perf_counter() - t0) / (self.step - start)
        shown = "".join(f"  {k} {values[k]:.4g}" for k in ("rec1", "rec2") if k in values)
        log.info("step %d/%d  G %.4g%s%s%s  %.2f s/step  ETA %.0f s", self.step, self.spec.steps,
                 values["generator_total"], shown, f"  D {values['critic_total']:.4g}" if "critic_total" in values
                 else "", self.progress_extra(values), rate, rate * (self.spec.steps - self.step + self.steps_after))

    def replicated_parameters(self) -> list[torch.Tensor]:
        """Parameters that must be identical on every rank (checked by check_replicas)."""
        return [p for m in self.model.generators() + self.model.critics() for p in m.parameters()]

    def check_replicas(self) -> float:
        """Under torchrun: the largest difference between a rank's parameters and rank 0's (0.0: identical, as
        DDP keeps them; a difference is logged, repaired from rank 0 and reported in metrics.json)."""
        if not self.dist.enabled:
            return 0.0
        diff = self.replica_check(self.replicated_parameters(), "parameters", "distributed/max_parameter_difference")
        self.replica_diff = max(self.replica_diff, diff)
        return diff

    def replica_check(self, params: list, what: str, tag: str) -> float:
        """Largest difference of ``params`` to rank 0's (repaired from rank 0 when non-zero), warned about and
        logged to TensorBoard as ``tag``. A collective: every rank calls it at the same step."""
        diff = distributed.replica_divergence(params, self.dist)
        if diff > 0:
            log.warning("step %d: %s differed between ranks by up to %.3g: reset to rank 0's", self.step, what, diff)
        if self.writer is not None:
            self.writer.add_scalar(tag, diff, self.step)
        return diff

    # ---- validation and logging ---------------------------------------------------------------------------
    def progress_extra(self, terms: dict) -> str:
        """Extra text for the console progress line (subclasses add what they train)."""
        return ""

    def restoring_modules(self) -> list[nn.Module]:
        """The generators used for evaluation: the EMA copies when EMA is on."""
        return self.ema.shadow if self.ema is not None else self.model.generators()

    @torch.no_grad()
    def validate(self, images: bool) -> dict:
        """PSNR / SSIM of the restoring modules on the fixed validation batch (field of view), logged to
        TensorBoard with, when ``images``, a panel of inputs, outputs and targets."""
        batch = self.data.validation_batch(self.spec.val_size)  # through the current mask (the data caches the rest)
        out = self.model.restore(batch["sensor"], self.data.otf, self.restoring_modules())
        n = self.data.image_size
        crop = lambda x: field_of_view(x, n).clamp(0, 1)  # noqa: E731
        b, t = crop(out["restored"]), crop(batch["scene"])
        metrics = {"val/psnr": float(psnr(b, t).mean()), "val/ssim": float(ssim(b, t).mean())}
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
        self.last_val = metrics
        return metrics

    def _log_scalars(self, terms: dict) -> None:
        if self.writer is None:
            return
        for k, v in terms.items():
            if k != "step":
                self.writer.add_scalar(f"loss/{k}", v, self.step)
        for k, v in self.model.scalars().items():
            self.writer.add_scalar(k, v, self.step)
        for opt, name in ((self.opt_g, "generator"), (self.opt_d, "critic")):
            for g in (opt.param_groups if opt is not None else ()):
                self.writer.add_scalar(f"lr/{name}_{g['name']}", g["lr"], self.step)

    # ---- checkpoints ----------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
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
            "record": {**self.record, "first_terms": self.first_terms, "last_val": self.last_val,
                       "lowest_terms": self.lowest_terms},
            "seconds": self.train_seconds,
        }

    def save(self, path: Path | None = None) -> Path:
        return save_checkpoint(path or self.run_dir / CHECKPOINT_NAME, self.state_dict())

    def load_state_dict(self, state: dict) -> None:
        self.model.load_state_dict(state["model"])
        self.opt_g.load_state_dict(state["opt_g"])
        self.sched_g.load_state_dict(state["sched_g"])
        if self.opt_d is not None:
            self.opt_d.load_state_dict(state["opt_d"])
            self.sched_d.load_state_dict(state["sched_d"])
        self.step = int(state["step"])
        record = dict(state.get("record") or {})  # absent in checkpoints written before it existed
        self.first_terms = dict(record.pop("first_terms", {}) or {})
        self.last_val = dict(record.pop("last_val", {}) or {})
        self.lowest_terms = dict(record.pop("lowest_terms", {}) or {})
        self.record = record
        self.seconds_before = float(state.get("seconds", 0.0))
        self._skips = torch.tensor([int(state.get("skipped", 0)), 0], dtype=torch.long, device=self.device)
        self._skips_reported = self._skips.tolist()
        if self.ema is not None:
            if state.get("ema"):
                self.ema.load_state_dict(state["ema"])
            else:  # EMA switched on at resume: start the average from the loaded weights, not the random init
                self.ema = EMA(self.model.generators(), self.ema.decay)
        rng = state["rng"]
        set_rng_state(rng)
        if rng.get("gp_device", "cpu") == self.gp_gen.device.type:
            self.gp_gen.set_state(rng["gp"])
        else:  # CPU and CUDA generators have different states: the next steps differ from the original run's
            log.warning("checkpoint from a %s run resumed on %s: gradient-penalty draws re-seeded",
                        rng.get("gp_device", "cpu"), self.gp_gen.device.type)
            self.gp_gen.manual_seed(int(self.step) + 2)
        self.data.load_state_dict(rng["data"])
