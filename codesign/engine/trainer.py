"""The restoration trainer: owns every optimizer, the GAN step order, schedules, EMA, logging and checkpoints.

Step order (one generator update), after one forward pass of the generators:
  1. critics (trainer.critic_steps times, when lambda_ADV > 0) on that pass's outputs detached:
     loss = lambda_ADV (E[D(fake)] - E[D(real)]) + lambda_GP GP for D1 and both D2 scales.
  2. generators, reusing the pass (they have not changed): critics frozen (requires_grad False), loss =
     adversarial + Charbonnier L1 (I_b; both scales of b) + MDF + VGG + FFT with the variant's weights.
Adam (betas of Sec. 6.2), weights and biases in separate groups (2e-4 / 4e-4), the Sec. 6.2 step schedule,
optional gradient clipping and generator EMA. A non-finite loss skips the update (logged, counted).
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
from codesign.engine.checkpoint import CHECKPOINT_NAME, rng_state, save_checkpoint, set_rng_state
from codesign.engine.train_spec import LossWeights, TrainerSpec
from codesign.models import SGAN, pyramid
from codesign.models.sgan import sandwich
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
    def update(self, modules: list[nn.Module]) -> None:
        for s, m in zip(self.shadow, modules):
            for ps, p in zip(s.parameters(), m.parameters()):
                ps.lerp_(p, 1.0 - self.decay)
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


class RestorationTrainer:
    """Train an SGAN on simulated batches from ``data`` (a RestorationData or anything with train_batch(step),
    validation_batch(n), otf, state_dict(), load_state_dict())."""

    def __init__(self, model: SGAN, data, spec: TrainerSpec, weights: LossWeights, run_dir: Path,
                 device: torch.device, config: dict, writer=None, seed: int = 0):
        self.model, self.data, self.spec, self.w = model.to(device), data, spec, weights
        self.run_dir, self.device, self.config, self.writer = Path(run_dir), device, config, writer
        if weights.vgg > 0:
            self.vgg, self.vgg_status = losses.build_vgg_loss(weights.vgg_weights, weights.vgg_layers)
        else:  # not part of this variant's objective: never load the weights
            self.vgg, self.vgg_status = None, "off: model.loss.vgg = 0 (not in this variant's objective)"
        if self.vgg is not None:
            self.vgg = self.vgg.to(device)
        gens, crits = model.generators(), model.discriminators()
        self.opt_g = torch.optim.Adam(param_groups(gens, spec.lr_weights, spec.lr_biases)
                                      + self.extra_generator_groups(), betas=spec.betas)
        self.opt_d = torch.optim.Adam(param_groups(crits, spec.lr_weights, spec.lr_biases), betas=spec.betas)
        self.sched_g = torch.optim.lr_scheduler.LambdaLR(self.opt_g, self.generator_lr_factors())
        self.sched_d = torch.optim.lr_scheduler.LambdaLR(self.opt_d, spec.lr_factor)
        self.ema = EMA(gens, spec.ema) if spec.ema else None
        self.gp_gen = torch.Generator(device=device).manual_seed(seed + 2)  # interpolation weights of the GP
        self.step = 0
        self.skipped = 0
        self.first_terms: dict = {}  # loss terms of the first and the last step of this process's run
        self.last_terms: dict = {}
        self._val = None

    # ---- losses ---------------------------------------------------------------------------------------------
    def _gp(self, critic, real, fake, cond=None):
        return losses.gradient_penalty(critic, real, fake, cond=cond, generator=self.gp_gen)

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
        d1 = losses.critic_loss(m.critic1(s, i_b)[0], m.critic1(s, fake_i)[0])
        d2 = sum(losses.critic_loss(m.d2[k](targets[k])[0], m.d2[k](fake_b[k])[0]) for k in range(2))
        total = w.adv * (d1 + d2)
        terms = {"d1_wasserstein": -d1, "d2_wasserstein": -d2}
        if w.gp > 0:  # the penalty's double backward is the critic step's largest cost: only when weighted
            gp1 = self._gp(m.d1, i_b, fake_i, m.condition1(s))
            gp2 = sum(self._gp(m.d2[k], targets[k], fake_b[k]) for k in range(2))
            total = total + w.gp * (gp1 + gp2)
            terms.update(d1_gp=gp1, d2_gp=gp2)
        terms["critic_total"] = total
        if not self._apply(self.opt_d, total, m.discriminators()):
            terms["critic_skipped"] = torch.tensor(1.0)
        return terms

    def generator_losses(self, batch: dict, out: dict) -> dict:
        m, w, eps = self.model, self.w, self.w.charbonnier_eps
        s, i_b = batch["sensor"], batch["irradiance"]
        targets = batch.get("targets") or pyramid(batch["scene"])
        terms = {"rec1": losses.charbonnier(out["i_b"], i_b, eps),
                 "rec2": sum(losses.charbonnier(out["b"][k], targets[k], eps) for k in range(2))}
        total = w.l1_stage1 * terms["rec1"] + w.l1_stage2 * terms["rec2"]
        if w.adv > 0 or w.mdf > 0:
            fake2 = [m.d2[k](out["b"][k]) for k in range(2)]
            if w.adv > 0:
                terms["adv"] = losses.generator_adv_loss(m.critic1(s, out["i_b"])[0]) + \
                    losses.generator_adv_loss([f[0] for f in fake2])
                total = total + w.adv * terms["adv"]
            if w.mdf > 0:
                with torch.no_grad():
                    real_feats = [m.d2[k](targets[k])[1] for k in range(2)]
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
        graph (the generators have not changed since they were computed); None = compute."""
        m = self.model
        crits = m.discriminators()
        set_requires_grad(crits, False)  # critics frozen: no gradient accumulates in them
        try:
            if out is None:
                out = m(batch["sensor"], batch.get("otf", self.data.otf))
            terms = self.generator_losses(batch, out)
        finally:
            set_requires_grad(crits, True)
        if not self._apply(self.opt_g, terms["generator_total"], m.generators()):
            terms["generator_skipped"] = torch.tensor(1.0)
        elif self.ema is not None:
            self.ema.update(m.generators())
        return terms

    def extra_generator_groups(self) -> list[dict]:
        """Parameter groups the generator optimizer steps beside the networks' (a trainable mask's)."""
        return []

    def generator_lr_factors(self) -> list:
        """One learning-rate factor function of the step per generator parameter group."""
        return [self.spec.lr_factor] * len(self.opt_g.param_groups)

    def extra_parameters(self, opt) -> list:
        """Parameters that ``opt`` updates beyond the modules' (a trainable mask): gradient-checked, not clipped."""
        return []

    def after_update(self, opt) -> None:
        """Called right after a successful ``opt.step()`` (a trainable mask projects itself here)."""

    def _apply(self, opt, loss: torch.Tensor, modules) -> bool:
        """Backward, clip, step; False (and no update) when the loss or a gradient is not finite."""
        opt.zero_grad(set_to_none=True)
        if not torch.isfinite(loss):
            self.skipped += 1
            log.warning("step %d: non-finite loss %s, update skipped", self.step, float(loss.detach()))
            return False
        loss.backward()
        params = [p for mod in modules for p in mod.parameters() if p.grad is not None]
        max_norm = self.spec.grad_clip if self.spec.grad_clip else math.inf
        norm = torch.nn.utils.clip_grad_norm_(params, max_norm)
        extra = [p.grad for p in self.extra_parameters(opt) if p.grad is not None]
        if not torch.isfinite(norm) or not all(bool(torch.isfinite(g).all()) for g in extra):
            opt.zero_grad(set_to_none=True)
            self.skipped += 1
            log.warning("step %d: non-finite gradient, update skipped", self.step)
            return False
        opt.step()
        self.after_update(opt)
        return True

    # ---- loop -----------------------------------------------------------------------------------------------
    def train_step(self) -> dict:
        """Critic update(s), then the generator update, on one simulated batch. The generators run once: the
        critic steps see their outputs detached, the generator step reuses them with their graph."""
        self.model.train()
        batch = self.data.train_batch(self.step)
        batch["targets"] = pyramid(batch["scene"])
        out = self.model(batch["sensor"], batch.get("otf", self.data.otf))
        terms = {}
        if self.w.adv > 0:
            for _ in range(self.spec.critic_steps):
                terms.update(self.critic_step(batch, out))
        terms.update(self.generator_step(batch, out))
        self.sched_g.step()
        self.sched_d.step()
        self.step += 1
        return {k: float(v.detach()) for k, v in terms.items()}

    def fit(self, progress_every: int = 10) -> list[dict]:
        spec = self.spec
        t0, start = time.perf_counter(), self.step
        while self.step < spec.steps:
            terms = self.train_step()
            terms["step"] = self.step
            self.first_terms = self.first_terms or terms
            self.last_terms = terms
            self._log_scalars(terms)
            over = spec.time_budget_s is not None and time.perf_counter() - t0 >= spec.time_budget_s
            last = self.step == spec.steps or over
            if spec.val_every and (self.step % spec.val_every == 0) or last:
                self._validate(images=last or bool(spec.image_every and self.step % spec.image_every == 0))
            if spec.checkpoint_every and self.step % spec.checkpoint_every == 0 or last:
                self.save()
            if self.step % progress_every == 0 or last or self.step == start + 1:
                rate = (time.perf_counter() - t0) / (self.step - start)
                log.info("step %d/%d  G %.4g  rec1 %.4g  rec2 %.4g%s%s  %.2f s/step  ETA %.0f s", self.step,
                         spec.steps, terms["generator_total"], terms["rec1"], terms["rec2"],
                         f"  D {terms['critic_total']:.4g}" if "critic_total" in terms else "",
                         self.progress_extra(terms), rate, rate * (spec.steps - self.step))
            if over:
                log.info("time budget of %.0f s reached at step %d/%d", spec.time_budget_s, self.step, spec.steps)
                break
        return [t for t in (self.first_terms, self.last_terms) if t]

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
            "config": self.config, "model_spec": dict(vars(self.model.spec)),
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
        self.step, self.skipped = int(state["step"]), int(state.get("skipped", 0))
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
