"""The restoration trainer: owns every optimizer, the GAN step order, schedules, EMA, logging and checkpoints.

Step order (one generator update), after one forward pass of the generators:
  1. critics (trainer.critic_steps times, when lambda_ADV > 0) on that pass's outputs detached:
     loss = lambda_ADV (E[D(fake)] - E[D(real)]) + lambda_GP GP for D1 and both D2 scales.
  2. generators, reusing the pass (they have not changed): critics frozen (requires_grad False), loss =
     adversarial + Charbonnier L1 (I_b; both scales of b) + MDF + VGG + FFT with the variant's weights.
Adam (betas of Sec. 6.2), weights and biases in separate groups (2e-4 / 4e-4), the Sec. 6.2 step schedule,
optional gradient clipping and generator EMA. A non-finite loss or gradient skips the update (counted, and
reported at the next logging step).

No host-device synchronization inside a step: losses stay on the device until a logging step reads them, and a
skipped update is decided on the device (Adam's fused kernel takes a ``found_inf`` flag, the protocol of
torch.amp.GradScaler), so a GPU never waits for the Python side. Under torchrun the networks run under
DistributedDataParallel (codesign/engine/distributed.py); only rank 0 validates, logs and writes checkpoints.
"""
from __future__ import annotations

import copy
import logging
import math
import time
from pathlib import Path

import torch
import torch.nn as nn

from codesign import losses
from codesign.engine import distributed
from codesign.engine.checkpoint import CHECKPOINT_NAME, rng_state, save_checkpoint, set_rng_state
from codesign.engine.train_spec import LossWeights, TrainerSpec
from codesign.models import SGAN, pyramid
from codesign.models.sgan import coordinates, sandwich
from codesign.quality import psnr, ssim

log = logging.getLogger("codesign.train")


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


def adam(groups: list[dict], betas, device: torch.device) -> torch.optim.Adam:
    """Adam with the fused kernel: one launch per step, and it honours the ``found_inf`` flag of a skipped update."""
    return torch.optim.Adam(groups, betas=betas, fused=device.type in ("cuda", "cpu"))


class RestorationTrainer:
    """Train an SGAN on simulated batches from ``data`` (a RestorationData or anything with train_batch(step),
    validation_batch(n), otf, state_dict(), load_state_dict()). ``dist``: the torchrun context (SINGLE: one
    process)."""

    def __init__(self, model: SGAN, data, spec: TrainerSpec, weights: LossWeights, run_dir: Path,
                 device: torch.device, config: dict, writer=None, seed: int = 0,
                 dist: distributed.DistContext = distributed.SINGLE):
        self.model, self.data, self.spec, self.w = model.to(device), data, spec, weights
        self.run_dir, self.device, self.config, self.writer = Path(run_dir), device, config, writer
        self.dist = dist
        if weights.vgg > 0:
            self.vgg, self.vgg_status = losses.build_vgg_loss(weights.vgg_weights, weights.vgg_layers)
        else:  # not part of this variant's objective: never load the weights
            self.vgg, self.vgg_status = None, "off: model.loss.vgg = 0 (not in this variant's objective)"
        if self.vgg is not None:
            self.vgg = self.vgg.to(device)
        gens, crits = model.generators(), model.discriminators()
        if spec.channels_last:
            model.to(memory_format=torch.channels_last)
        # the modules the training step runs: DDP wrappers sharing the model's parameters under torchrun, G1 and
        # G2 optionally compiled
        self.train_generators = [distributed.wrap(g, dist, device) for g in gens]
        if spec.compile:
            self.train_generators = [torch.compile(g) if k != 1 else g for k, g in enumerate(self.train_generators)]
        self.train_d1 = distributed.wrap(model.d1, dist, device)
        self.train_d2 = [distributed.wrap(d, dist, device) for d in model.d2]
        self.opt_g = adam(param_groups(gens, spec.lr_weights, spec.lr_biases) + self.extra_generator_groups(),
                          spec.betas, device)
        self.opt_d = adam(param_groups(crits, spec.lr_weights, spec.lr_biases), spec.betas, device)
        self.sched_g = torch.optim.lr_scheduler.LambdaLR(self.opt_g, self.generator_lr_factors())
        self.sched_d = torch.optim.lr_scheduler.LambdaLR(self.opt_d, spec.lr_factor)
        self.ema = EMA(gens, spec.ema) if spec.ema else None
        self.gp_gen = torch.Generator(device=device).manual_seed(seed + 2)  # interpolation weights of the GP
        self.step = 0
        self._skips = torch.zeros(2, dtype=torch.long, device=device)  # updates skipped: non-finite loss, gradient
        self._skips_reported = [0, 0]
        self.replica_diff = 0.0  # largest weight difference between ranks found by the last check
        self.first_terms: dict = {}  # loss terms of the first and the last step of this process's run
        self.last_terms: dict = {}
        self._val = None

    # ---- losses ---------------------------------------------------------------------------------------------
    @property
    def skipped(self) -> int:
        """Updates skipped so far (reads the device counter: a host sync)."""
        return int(self._skips.sum())

    def _gp(self, critic, real, fake, cond=None):
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

    def _critic1(self, sensor: torch.Tensor, i_b: torch.Tensor):
        """D1(s, x, y, I_b) through the training wrapper (model.critic1 runs the plain module)."""
        return self.run(self.train_d1, torch.cat([sensor, coordinates(sensor), i_b], 1))

    def critic_step(self, batch: dict, out: dict | None = None) -> dict:
        """One critic update. ``out``: the generators' outputs for this batch (detached here); None = compute."""
        m, w = self.model, self.w
        # detached: with a trainable mask the sensor image carries the optics' graph, which the critics'
        # update must neither consume nor write gradients into
        s, i_b = batch["sensor"].detach(), batch["irradiance"].detach()
        targets = batch.get("targets") or pyramid(batch["scene"])
        if out is None:
            with torch.no_grad():
                out = m(s, batch.get("otf", self.data.otf))
        fake_i, fake_b = out["i_b"].detach(), [b.detach() for b in out["b"]]
        d2n = self.train_d2
        d1 = losses.critic_loss(self._critic1(s, i_b)[0], self._critic1(s, fake_i)[0])
        d2 = sum(losses.critic_loss(self.run(d2n[k], targets[k])[0], self.run(d2n[k], fake_b[k])[0])
                 for k in range(2))
        total = w.adv * (d1 + d2)
        terms = {"d1_wasserstein": -d1, "d2_wasserstein": -d2}
        if w.gp > 0:  # the penalty's double backward is the critic step's largest cost: only when weighted
            gp1 = self._gp(self.train_d1, i_b, fake_i, m.condition1(s))
            gp2 = sum(self._gp(d2n[k], targets[k], fake_b[k]) for k in range(2))
            total = total + w.gp * (gp1 + gp2)
            terms.update(d1_gp=gp1, d2_gp=gp2)
        terms["critic_total"] = total
        terms["critic_skipped"] = (~self._apply(self.opt_d, total, m.discriminators())).float()
        return terms

    def generator_losses(self, batch: dict, out: dict) -> dict:
        m, w, eps = self.model, self.w, self.w.charbonnier_eps
        s, i_b = batch["sensor"], batch["irradiance"]
        targets = batch.get("targets") or pyramid(batch["scene"])
        terms = {"rec1": losses.charbonnier(out["i_b"], i_b, eps),
                 "rec2": sum(losses.charbonnier(out["b"][k], targets[k], eps) for k in range(2))}
        total = w.l1_stage1 * terms["rec1"] + w.l1_stage2 * terms["rec2"]
        if w.adv > 0 or w.mdf > 0:
            fake2 = [self.run(m.d2[k], out["b"][k]) for k in range(2)]
            if w.adv > 0:
                terms["adv"] = losses.generator_adv_loss(self.run(m.critic1, s, out["i_b"])[0]) + \
                    losses.generator_adv_loss([f[0] for f in fake2])
                total = total + w.adv * terms["adv"]
            if w.mdf > 0:
                with torch.no_grad():
                    real_feats = [self.run(m.d2[k], targets[k])[1] for k in range(2)]
                terms["mdf"] = losses.feature_matching_loss(real_feats, [f[1] for f in fake2])
                total = total + w.mdf * terms["mdf"]
        if w.vgg > 0 and self.vgg is not None:
            terms["vgg"] = sum(self.vgg(out["b"][k], targets[k]) for k in range(2))
            total = total + w.vgg * terms["vgg"]
        if w.fft > 0:
            terms["fft"] = sum(losses.fft_loss(out["b"][k], targets[k]) for k in range(2))
            total = total + w.fft * terms["fft"]
        terms["generator_total"] = total
        return terms

    def generator_step(self, batch: dict, out: dict | None = None) -> dict:
        """One generator update with every critic frozen. ``out``: this batch's generator outputs with their
        graph (the generators have not changed since they were computed); None = compute. The frozen critics
        run as plain modules (no DDP: they take no update here)."""
        m = self.model
        crits = m.discriminators()
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
        return self.run(lambda s, otf: sandwich(self.train_generators, s, otf, self.model.spec.g1_residual),
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
        if opt.defaults.get("fused"):
            opt.found_inf = skip.to(torch.float32)  # torch.optim's fused-step protocol (torch.amp.GradScaler's)
            try:
                opt.step()
            finally:
                del opt.found_inf
        elif not bool(skip):  # a device without the fused kernel decides on the host
            opt.step()
        applied = ~skip
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

    # ---- loop -----------------------------------------------------------------------------------------------
    def train_step(self) -> dict:
        """Critic update(s), then the generator update, on one simulated batch. The generators run once: the
        critic steps see their outputs detached, the generator step reuses them with their graph. Returns the
        loss terms as detached 0-dim tensors on the device (this rank's batch share)."""
        self.model.train()
        batch = self.data.train_batch(self.step)
        batch["targets"] = pyramid(batch["scene"])
        out = self.generate(batch)
        terms = {}
        if self.w.adv > 0:
            for _ in range(self.spec.critic_steps):
                terms.update(self.critic_step(batch, out))
        terms.update(self.generator_step(batch, out))
        self.sched_g.step()
        self.sched_d.step()
        self.step += 1
        return {k: v.detach() for k, v in terms.items()}

    def fit(self, progress_every: int = 10) -> list[dict]:
        """Train to spec.steps (or the time budget). Loss terms are read (averaged over the ranks) only every
        ``progress_every`` steps, the first and the last: the console, TensorBoard and the returned
        [first, last] terms see those steps; in between the device runs ahead of the host."""
        spec = self.spec
        t0, start = time.perf_counter(), self.step
        while self.step < spec.steps:
            terms = self.train_step()
            over = spec.time_budget_s is not None and time.perf_counter() - t0 >= spec.time_budget_s
            if self.dist.enabled and spec.time_budget_s is not None:  # all ranks stop together: rank 0's clock
                over = distributed.broadcast_flag(over, self.dist)
            last = self.step == spec.steps or over
            if self.step % progress_every == 0 or last or self.step == start + 1:
                self._log_step(terms, t0, start)
            if spec.val_every and (self.step % spec.val_every == 0) or last:
                self.check_replicas()
                if self.dist.is_main:
                    self._validate(images=last or bool(spec.image_every and self.step % spec.image_every == 0))
            if (spec.checkpoint_every and self.step % spec.checkpoint_every == 0 or last) and self.dist.is_main:
                self.save()
            if over:
                log.info("time budget of %.0f s reached at step %d/%d", spec.time_budget_s, self.step, spec.steps)
                break
        return [t for t in (self.first_terms, self.last_terms) if t]

    def _log_step(self, terms: dict, t0: float, start: int) -> None:
        """Read this step's terms (global-batch means), log them and the skips; the progress line."""
        values = distributed.all_mean(terms, self.dist)
        values["step"] = self.step
        self.first_terms = self.first_terms or values
        self.last_terms = values
        self.report_skips()
        if self.dist.is_main:
            self._log_scalars(values)
        rate = (time.perf_counter() - t0) / (self.step - start)
        log.info("step %d/%d  G %.4g  rec1 %.4g  rec2 %.4g%s%s  %.2f s/step  ETA %.0f s", self.step,
                 self.spec.steps, values["generator_total"], values["rec1"], values["rec2"],
                 f"  D {values['critic_total']:.4g}" if "critic_total" in values else "",
                 self.progress_extra(values), rate, rate * (self.spec.steps - self.step))

    def replicated_parameters(self) -> list[torch.Tensor]:
        """Parameters that must be identical on every rank (checked by check_replicas)."""
        return [p for m in self.model.generators() + self.model.discriminators() for p in m.parameters()]

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
    def _validate(self, images: bool) -> dict:
        if self._val is None:
            self._val = self.data.validation_batch(self.spec.val_size)
        batch = self._val
        out = restore_with(self.model, self.restoring_modules(), batch["sensor"], self.data.otf)
        n = self.data.image_size
        crop = lambda x: centre(x, n).clamp(0, 1)  # noqa: E731
        b, t = crop(out["b"][1]), crop(batch["scene"])
        metrics = {"val/psnr": float(psnr(b, t).mean()), "val/ssim": float(ssim(b, t).mean()),
                   "val/psnr_i_b": float(psnr(crop(out["i_b"]), crop(batch["irradiance"])).mean())}
        if self.writer is not None:
            for k, v in metrics.items():
                self.writer.add_scalar(k, v, self.step)
            if images:
                k = min(4, batch["sensor"].shape[0])
                panel = {"sensor_input": batch["sensor"][:k], "pre_restored_i_b": out["i_b"][:k],
                         "restored_b": out["b"][1][:k], "ground_truth_b": batch["scene"][:k],
                         "target_i_b": batch["irradiance"][:k]}
                for name, img in panel.items():
                    self.writer.add_images(f"images/{name}", img.clamp(0, 1).cpu(), self.step)
            self.writer.flush()
        self.last_val = metrics
        return metrics

    def _log_scalars(self, terms: dict) -> None:
        if self.writer is None:
            return
        for k, v in terms.items():
            if k != "step":
                self.writer.add_scalar(f"loss/{k}", v, self.step)
        gamma = self.model.gv.deconv.gamma.detach()
        self.writer.add_scalar("wiener/gamma_mean", float(gamma.mean()), self.step)
        self.writer.add_scalar("wiener/gamma_min", float(gamma.min()), self.step)
        self.writer.add_scalar("wiener/gamma_max", float(gamma.max()), self.step)
        for opt, name in ((self.opt_g, "generator"), (self.opt_d, "critic")):
            for g in opt.param_groups:
                self.writer.add_scalar(f"lr/{name}_{g['name']}", g["lr"], self.step)

    # ---- checkpoints ----------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "model": self.model.state_dict(), "opt_g": self.opt_g.state_dict(), "opt_d": self.opt_d.state_dict(),
            "sched_g": self.sched_g.state_dict(), "sched_d": self.sched_d.state_dict(), "step": self.step,
            "skipped": self.skipped, "ema": self.ema.state_dict() if self.ema else None,
            "rng": {**rng_state(), "gp": self.gp_gen.get_state(), "gp_device": self.gp_gen.device.type,
                    "data": self.data.state_dict()},
            "config": self.config, "model_spec": dict(vars(self.model.spec)), "world_size": self.dist.world,
            "versions": {"torch": str(torch.__version__)},
        }

    def save(self, path: Path | None = None) -> Path:
        return save_checkpoint(path or self.run_dir / CHECKPOINT_NAME, self.state_dict())

    def load_state_dict(self, state: dict) -> None:
        self.model.load_state_dict(state["model"])
        self.opt_g.load_state_dict(state["opt_g"])
        self.opt_d.load_state_dict(state["opt_d"])
        self.sched_g.load_state_dict(state["sched_g"])
        self.sched_d.load_state_dict(state["sched_d"])
        self.step = int(state["step"])
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


def centre(x: torch.Tensor, n: int) -> torch.Tensor:
    """The central n x n of a padded (..., P, P) map: the sensor's field of view."""
    p = x.shape[-1]
    m = (p - n) // 2
    return x[..., m:m + n, m:m + n]


def restore_with(model: SGAN, generators: list[nn.Module], sensor: torch.Tensor, otf: torch.Tensor) -> dict:
    """Run the sandwich with the given (g1, gv, g2) modules (e.g. EMA copies) in eval mode."""
    modes = [g.training for g in generators]
    for g in generators:
        g.eval()
    try:
        return sandwich(generators, sensor, otf, model.spec.g1_residual)
    finally:
        for g, mode in zip(generators, modes):
            g.train(mode)
