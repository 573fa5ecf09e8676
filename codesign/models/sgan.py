"""The sandwich GAN, Eq. (image_restore_model):  b^ = G2(G_v(G1(s, x, y), h)).

  G1  residual UNet on (s, x, y) -> I_b^ (pre-restored irradiance: laser inpainted, border outpainted, denoised)
  G_v FE (CRRR16, kernel 5) -> learnable Wiener deconvolution of each feature with the system OTF
  G2  residual UNet on two scales: per-scale input layers, shared body; coarse = features downsampled 2x with
      antialiased bicubic; outputs [b^0 (coarse), b^1 (fine)]
  D1  conditional PatchGAN on (s, x, y, I_b);  D2 = {D2^0, D2^1} PatchGANs on b^L
"""
from __future__ import annotations

import logging
import math
from typing import Mapping

import torch
import torch.nn as nn
import torch.nn.functional as F

from codesign.camera import field_of_view
from codesign.config.store import register, spec_node
from codesign.models import losses
from codesign.models.discriminators import PatchDiscriminator
from codesign.models.fill import field_size, saturated_fraction
from codesign.models.level import LevelHead, best_log_gain, fit_weight, level_features
from codesign.models.losses import LossWeights
from codesign.models.restorer import Restorer, TrainContext
from codesign.models.sandwich import (coordinates, downsample2, laser_presence, level_presence, plain_module,
                                      pyramid, sandwich)
from codesign.models.spec import ModelSpec
from codesign.models.unet import ResUNet, UNetBody, make_head, zero_conv
from codesign.models.wiener import DeconvModule, wiener_filter

log = logging.getLogger("codesign.train")
LEVEL_FIT_CHUNK = 8  # the level head's fit crops (trainer.calibrate_crops) are restored in chunks of this many



class Refiner(nn.Module):
    """G2: one head per scale (the first ``head_layers`` layers), one shared UNet body."""

    def __init__(self, spec: ModelSpec):
        super().__init__()
        n = spec.fe_features
        self.coarse_to_fine = spec.coarse_to_fine
        self.heads = nn.ModuleList([make_head(n, spec.stem_width, spec.g2_head_layers),
                                    make_head(n + int(spec.coarse_to_fine), spec.stem_width, spec.g2_head_layers)])
        self.body = UNetBody(spec.stem_width, spec.widths, 1, spec.generator_block, spec.attention,
                             spec.key_channels)
        self.skip = zero_conv(n, 1, 1) if spec.g2_linear_skip else None
        # model.g2_base=wiener: the log noise-to-signal ratio of the classical Wiener filter G2's residual corrects
        self.log_nsr = nn.Parameter(torch.tensor(math.log(spec.g2_base_nsr))) if spec.g2_base == "wiener" else None
        # model.laser_gate: the saturated fraction at which presence is 1/2, and the lasered images' log nsr
        self.log_f0 = nn.Parameter(torch.tensor(math.log(spec.laser_gate_f0))) if spec.laser_gate else None
        self.level = LevelHead() if spec.level_head else None  # model.level_head
        self.log_nsr_lasered = (nn.Parameter(torch.tensor(math.log(spec.g2_base_nsr_lasered)))
                                if spec.laser_gate and spec.g2_base == "wiener" else None)

    def laser_presence(self, sensor: torch.Tensor) -> torch.Tensor:
        """(B,) p = f / (f + f0) in [0, 1): 0 for an image without saturated pixels (model.laser_gate)."""
        f = saturated_fraction(sensor)
        return f / (f + self.log_f0.exp())

    def base(self, i_b: torch.Tensor, otf: torch.Tensor, presence: torch.Tensor | None = None) -> torch.Tensor:
        """What G2's outputs correct (model.g2_residual): I_b^, or its Wiener deconvolution with the system OTF
        scaled to unit DC gain (with ``presence``, at a log nsr between the unlasered and lasered values)."""
        base = i_b
        if self.log_nsr is not None:
            log_nsr = self.log_nsr
            if presence is not None and self.log_nsr_lasered is not None:
                log_nsr = (log_nsr + presence * (self.log_nsr_lasered - log_nsr))[:, None, None, None]
            nsr = log_nsr.exp()
            # at unit DC gain: Wiener's DC gain H(0) / (|H(0)|^2 + nsr) is 1 / 101 at the lasered images' nsr ~ 100,
            # and a base that dark leaves G2's correction to draw the whole image (docs/models.md Sec. 10)
            dc = otf[..., 0, 0].real
            base = wiener_filter(i_b, otf, 1.0, nsr) * ((dc * dc + nsr) / dc)
        return base

    def _scale(self, head: nn.Module, x: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        out = self.body(head(x))
        return out if self.skip is None else out + self.skip(features)

    def forward(self, features: torch.Tensor, base: torch.Tensor | None = None,
                gate: torch.Tensor | None = None) -> list[torch.Tensor]:
        """[coarse, fine] estimates; ``base`` (B, 1, P, P): added to them (downsampled for the coarse one), so that
        G2 learns a correction to it (model.g2_residual); ``gate`` (B,): scales that correction per image
        (model.g2_gate)."""
        g = 1.0 if gate is None else gate[:, None, None, None]
        small = downsample2(features)
        coarse = self._scale(self.heads[0], small, small)
        if base is not None:
            coarse = g * coarse + downsample2(base)
        fine_in = features
        if self.coarse_to_fine:
            up = F.interpolate(coarse, size=features.shape[-2:], mode="bicubic", align_corners=False)
            fine_in = torch.cat([features, up], 1)
        fine = self._scale(self.heads[1], fine_in, features)
        return [coarse, fine if base is None else g * fine + base]


class SGAN(Restorer):
    """The sandwich GAN b^ = G2(G_v(G1(s, x, y), h)) with its critics D1, D2^0, D2^1 and its objective.

    Args:
        spec: the architecture (variant B/E/F, widths); weights: the variant's loss weights (model.loss).
    """

    kind = "sgan"
    method = "sgan"

    def __init__(self, spec: ModelSpec, weights: LossWeights | None = None):
        super().__init__()
        self.spec = spec
        self.weights = weights if weights is not None else LossWeights()
        g, d = spec.generator_block, spec.critic_block
        self.g1 = ResUNet(3 + int(spec.g1_halo), 1, spec.stem_width, spec.widths, g, spec.attention,
                          key_channels=spec.key_channels)
        self.gv = DeconvModule(spec.fe_features, spec.fe_kernel, spec.gamma_init)
        self.g2 = Refiner(spec)
        self.d1 = PatchDiscriminator(4, spec.d_widths, d, spec.attention, key_channels=spec.key_channels)
        self.d2 = nn.ModuleList([PatchDiscriminator(1, spec.d_widths, d, spec.attention, key_channels=spec.key_channels)
                                 for _ in range(2)])
        self.vgg, self._vgg_status = None, "off: not prepared for training"

    @classmethod
    def from_config(cls, cfg: Mapping) -> "SGAN":
        """From a ``model`` block: the architecture keys (ModelSpec) and ``loss`` (LossWeights)."""
        values = {k: v for k, v in dict(cfg).items() if k not in ("loss", "kind")}
        return cls(ModelSpec.from_config(values), LossWeights.from_config(dict(cfg.get("loss") or {})))

    # ---- parts --------------------------------------------------------------------------------------------------
    def generators(self) -> list[nn.Module]:
        """[G1, G_v, G2]: the three stages of the sandwich, in the order ``forward_with`` runs them."""
        return [self.g1, self.gv, self.g2]

    def critics(self) -> list[nn.Module]:
        """D1 and the two scales of D2, each its own module (DDP wraps them one by one)."""
        return [self.d1, self.d2[0], self.d2[1]]

    @property
    def adversarial(self) -> bool:
        """Whether the critics are trained: the variant weights the adversarial term (model.loss.adv > 0)."""
        return self.weights.adv > 0

    def prepare_training(self, device: torch.device) -> None:
        """The VGG19 perceptual loss, loaded from model.loss.vgg_weights when this variant weights it."""
        if self.weights.vgg > 0:
            self.vgg, self._vgg_status = losses.build_vgg_loss(self.weights.vgg_weights, self.weights.vgg_layers)
        else:  # not part of this variant's objective: never load the weights
            self.vgg, self._vgg_status = None, "off: model.loss.vgg = 0 (not in this variant's objective)"
        if self.vgg is not None:
            self.vgg = self.vgg.to(device)

    @property
    def loss_status(self) -> str:
        """The VGG loss's state as ``prepare_training`` left it: "on: <weights path>" or "off: <why>"."""
        return self._vgg_status

    @torch.no_grad()
    def calibrate(self, generators, data, crops: int, refit: bool = False) -> dict:
        """model.level_head: fit the gain head on training-split crops drawn as in training, ``crops`` / 2 scenes
        each imaged without a laser and with the laser drawn for it (the validation batch's scenes and parameters,
        every alpha_b of the training distribution), restored by ``generators`` with the head off. The fit is of
        the head as it is applied: held to the scene, the log gain times 1 - p (the laser's presence,
        model.laser_gate; level_presence), so a dazzled image G2 restores weighs by how much of the gain it gets.
        The weight goes into the model and into ``generators``' G2. A head already fitted (a warm start's: the
        shipped network's was fitted on 1,024 crops) is kept unless ``refit``: what it scales keeps its level through
        a fine-tuning, the unit-DC Wiener base of a gated G2 without a laser, or, held to the exposure
        (target_level), G2's output, which training holds at the sensor's level."""
        if not self.spec.level_head:
            return {}
        heads = [plain_module(generators[2]).level, self.g2.level]
        if heads[0].fitted and not refit:
            return {"level_head": "kept (fitted before this training)"}
        for h in heads:
            h.set_weight(torch.zeros_like(h.weight))
        rows, logs = [], []
        half = crops // 2
        for batch in (data.unlasered_batch(half), data.validation_batch(half)):
            for k in range(0, half, LEVEL_FIT_CHUNK):
                sensor, scene = batch["sensor"][k:k + LEVEL_FIT_CHUNK], batch["scene"][k:k + LEVEL_FIT_CHUNK]
                out = self.restore(sensor, data.otf, generators)["restored"]
                presence = level_presence(laser_presence(generators[2], sensor, self.spec), self.spec)
                keep = 1.0 if presence is None else (1 - presence.double())[:, None]
                rows.append(level_features(out, sensor) * keep)
                logs.append(best_log_gain(out, scene, sensor > 0))
        f, t = torch.cat(rows), torch.cat(logs)
        weight = fit_weight(f, t)
        for h in heads:
            h.set_weight(weight.to(h.weight))
        ok = torch.isfinite(t)
        pred = (f @ weight.to(f))[ok]
        r2 = 1 - float((t[ok] - pred).var() / t[ok].var())
        fact = {"crops": int(ok.sum()), "r2": round(r2, 4), "gain_min": float(pred.exp().min()),
                "gain_max": float(pred.exp().max())}
        log.info("model.level_head fitted on %d training crops (half without a laser): gain %.3g to %.3g, R^2 %.2f "
                 "of the best log gains", fact["crops"], fact["gain_min"], fact["gain_max"], r2)
        return {"level_head": fact}

    # ---- restoring ----------------------------------------------------------------------------------------------
    def forward_with(self, generators, sensor: torch.Tensor, otf: torch.Tensor) -> dict:
        """sensor (B, 1, P, P); otf (P, P // 2 + 1) of the system PSF kernel at the network pitch. Returns i_b
        (B,1,P,P), features (B,N,P,P) after deconvolution, b = [b^0 (B,1,P/2,P/2), b^1 (B,1,P,P)], restored = b^1."""
        return sandwich(generators, sensor, otf, self.spec)

    def critic1(self, sensor: torch.Tensor, i_b: torch.Tensor):
        """D1(s, x, y, I_b) -> (patch scores, level features)."""
        return self.d1(torch.cat([sensor, coordinates(sensor), i_b], 1))

    def condition1(self, sensor: torch.Tensor) -> torch.Tensor:
        """The conditioning channels of D1: (s, x, y)."""
        return torch.cat([sensor, coordinates(sensor)], 1)

    # ---- the objective (supplement, "Hyper-parameters in Training") --------------------------------------------
    def critic_losses(self, batch: dict, out: dict, ctx: TrainContext) -> dict:
        """WGAN critic terms for D1 (conditional on s) and both D2 scales, with the gradient penalty when weighted.
        Inputs detached: with a trainable mask the sensor image carries the optics' graph, which the critics'
        update must neither consume nor write gradients into."""
        w = self.weights
        s, i_b = batch["sensor"].detach(), batch["irradiance"].detach()
        targets = _targets(batch, self.spec.target_level)
        fake_i, fake_b = out["i_b"].detach(), [b.detach() for b in _held(out)]
        d1n, d2n = ctx.critics[0], ctx.critics[1:]
        critic1 = lambda x: ctx.run(d1n, torch.cat([s, coordinates(s), x], 1))[0]  # noqa: E731
        d1 = losses.critic_loss(critic1(i_b), critic1(fake_i))
        d2 = sum(losses.critic_loss(ctx.run(d2n[k], targets[k])[0], ctx.run(d2n[k], fake_b[k])[0]) for k in range(2))
        total = w.adv * (d1 + d2)
        terms = {"d1_wasserstein": -d1, "d2_wasserstein": -d2}
        if w.gp > 0:  # the penalty's double backward is the critic step's largest cost: only when weighted
            gp1 = ctx.gradient_penalty(d1n, i_b, fake_i, self.condition1(s))
            gp2 = sum(ctx.gradient_penalty(d2n[k], targets[k], fake_b[k]) for k in range(2))
            total = total + w.gp * (gp1 + gp2)
            terms.update(d1_gp=gp1, d2_gp=gp2)
        terms["critic_total"] = total
        return terms

    def generator_losses(self, batch: dict, out: dict, ctx: TrainContext) -> dict:
        """Charbonnier L1 on I_b and both scales of b, adversarial, MDF, VGG and FFT terms with the variant's
        weights. The critics run as plain modules (frozen by the trainer: they take no update here)."""
        w, eps = self.weights, self.weights.charbonnier_eps
        s, i_b = batch["sensor"], batch["irradiance"]
        targets, b = _targets(batch, self.spec.target_level), _held(out)
        # the images the compared terms take (model.loss.region): the canvas, or the sensor's field alone; the
        # critics below judge the canvas either way
        ci, ti, cb, tb = out["i_b"], i_b, b, targets
        if w.region == "field":
            n = field_size(s)
            ci, ti = _field(ci, n, s), _field(ti, n, s)
            cb, tb = [_field(x, n, s) for x in b], [_field(x, n, s) for x in targets]
        terms = {"rec1": losses.charbonnier(ci, ti, eps),
                 "rec2": sum(losses.charbonnier(cb[k], tb[k], eps) for k in range(2))}
        total = w.l1_stage1 * terms["rec1"] + w.l1_stage2 * terms["rec2"]
        if w.adv > 0 or w.mdf > 0:
            fake2 = [ctx.run(self.d2[k], b[k]) for k in range(2)]
            if w.adv > 0:
                terms["adv"] = losses.generator_adv_loss(ctx.run(self.critic1, s, out["i_b"])[0]) + \
                    losses.generator_adv_loss([f[0] for f in fake2])
                total = total + w.adv * terms["adv"]
            if w.mdf > 0:
                with torch.no_grad():
                    real_feats = [ctx.run(self.d2[k], targets[k])[1] for k in range(2)]
                terms["mdf"] = losses.feature_matching_loss(real_feats, [f[1] for f in fake2])
                total = total + w.mdf * terms["mdf"]
        if w.vgg > 0 and self.vgg is not None:
            terms["vgg"] = sum(self.vgg(cb[k], tb[k]) for k in range(2))
            total = total + w.vgg * terms["vgg"]
        if w.fft > 0:
            terms["fft"] = sum(losses.fft_loss(cb[k], tb[k]) for k in range(2))
            total = total + w.fft * terms["fft"]
        terms["generator_total"] = total
        return terms

    # ---- reporting ----------------------------------------------------------------------------------------------
    def summary(self) -> dict:
        """The network's name (model.name, default its variant), its variant (sgan_b/e/f) and its size."""
        return {"network": self.spec.name, "variant": self.spec.variant, "size": self.spec.size}

    def scalars(self) -> dict[str, float]:
        """Mean, min and max of G_v's learned Wiener noise powers gamma_i (``wiener/gamma_*``)."""
        gamma = self.gv.deconv.gamma.detach()
        return {"wiener/gamma_mean": float(gamma.mean()), "wiener/gamma_min": float(gamma.min()),
                "wiener/gamma_max": float(gamma.max())}

    def check_input_size(self, padded_size: int, key: str = "data.padded_size") -> None:
        """ConfigError naming ``key`` unless ``padded_size`` is even and its coarse half fits the UNet depth and the
        critics' patches (ModelSpec.check_input_size)."""
        self.spec.check_input_size(padded_size, key)


def _field(x: torch.Tensor, n: int, sensor: torch.Tensor) -> torch.Tensor:
    """The sensor's field (``n`` of ``sensor``'s P pixels, centred) of ``x`` at its own scale (G2's coarse output
    and target are at P / 2, their field n / 2)."""
    return field_of_view(x, n * x.shape[-1] // sensor.shape[-1])


def _held(out: dict) -> list[torch.Tensor]:
    """The two scales the objective holds to _targets: held to the exposure (model.target_level: the sandwich keeps
    "b_exposure"), G2's output before the level head's gain, which is fitted apart and brings it to the scene's level
    only in use (a head fitted before or during training, a warm start's or a resumed finished run's, would otherwise
    scale every output away from its target); held to the scene, the output the head has already scaled (1 - p of
    its gain per image)."""
    return out.get("b_exposure", out["b"])


def _targets(batch: dict, level: str = "scene") -> list[torch.Tensor]:
    """[coarse, fine] targets of G2, computed once per batch and kept in it: the scene, or with ``level``
    "exposure" the scene at the exposure the sensor saw, alpha_b * b (model.target_level)."""
    if batch.get("targets") is None:
        scene = batch["scene"]
        if level == "exposure":
            if batch.get("alpha_b") is None:
                raise ValueError("model.target_level=exposure needs the batch's alpha_b (B,), which "
                                 "SimulatedData.simulate provides; this batch has none")
            scene = scene * batch["alpha_b"].to(scene)[:, None, None, None]
        batch["targets"] = pyramid(scene)
    return batch["targets"]


# The loss weights of each variant (supplement, Table "Values of Hyperparameters in Model Training"); the rest of the
# variant is LossWeights' defaults, SGAN-B's: s1 200, s2 50, ADV 1, GP 10; its "VGG 50" column contradicts Eq.
# (TotalObj_B) (B has no VGG term) and is read as lambda_MDF = 50. SGAN-E adds the VGG perceptual loss and SGAN-F
# the FFT loss (ortho normalization); both VGG terms stay off, and say so in metrics.json, without vgg_weights.
VARIANT_LOSSES: dict[str, dict[str, float]] = {
    "sgan_b": {},
    "sgan_e": {"l1_stage1": 300.0, "l1_stage2": 50.0, "mdf": 100.0, "vgg": 100.0, "adv": 0.1, "gp": 1.0},
    "sgan_f": {"l1_stage1": 10.0, "l1_stage2": 10.0, "mdf": 0.1, "vgg": 0.1, "fft": 100.0, "adv": 0.1, "gp": 1.0},
}
for _variant, _loss in VARIANT_LOSSES.items():  # the config options model=sgan_b|sgan_e|sgan_f
    register("model", _variant, {"kind": SGAN.kind, **spec_node(ModelSpec, name=_variant, variant=_variant),
                                 "loss": spec_node(LossWeights, **_loss)})

# model=sgan_b_gated, the main job's network before sgan_b_l1 below: SGAN-B whose untrained sandwich is the laser-aware
# classical pipeline (G1 corrects the filled sensor image, G2 the unit-DC Wiener deconvolution of I_b^ at an nsr
# that follows the laser's presence) and whose learned corrections are gated by that presence: the options that
# keep it above the sensor image and ahead of Wiener from the first steps (docs/models.md Sec. 10); and tuned to the
# mask it restores: the base's nsr set per mask before a run from fresh weights, as the classical floor is, and a
# laser's presence counted from 1 % of saturated pixels, so that a weak laser's few saturated pixels (alpha_l = 1e3)
# leave the image to that tuned base (the main job's measurements: docs/codesign.md Sec. 7); and brought to the
# scene's level by a gain per image fitted at the end of training (model.level_head, docs/models.md Sec. 12)
GATED = {"g2_residual": True, "g1_base": "filled", "g2_base": "wiener", "laser_gate": True,
         "g2_base_nsr_lasered": 100.0, "g2_gate": True, "laser_gate_f0": 1e-2, "g2_base_nsr_tuned": True,
         "level_head": True}
_GATED_NODE = spec_node(ModelSpec, name="sgan_b_gated", variant="sgan_b", **GATED)
register("model", "sgan_b_gated", {"kind": SGAN.kind, **_GATED_NODE, "loss": spec_node(LossWeights)})

# model=sgan_b_l1, the main job's network (+experiment=joint, which also spaces the training lasers geometrically:
# data.params.alpha_l_spacing=log) and the shipped one's: sgan_b_gated with G2's correction not gated by the laser's
# presence, so that it can pass Wiener without a laser; G2 held to the sensor's exposure, which the level head then
# scales to the scene's; and its reconstruction (L1) terms alone, which learned faster than with the adversarial
# ones and take no critic work (docs/models.md Sec. 13); since 2026-11-29 its Wiener base deconvolves I_b^ with the
# field's border replicated into the padding, as the classical floor does (model.g2_base_pad: +0.3 dB for the main
# job's systems without a laser; the shipped weights, trained on the filled padding, keep theirs when loaded alone)
L1_RECIPE = {**GATED, "g2_gate": False, "target_level": "exposure", "g2_base_pad": "replicate"}
_L1_NODE = spec_node(ModelSpec, name="sgan_b_l1", variant="sgan_b", **L1_RECIPE)
register("model", "sgan_b_l1", {"kind": SGAN.kind, **_L1_NODE, "loss": spec_node(LossWeights, adv=0.0, mdf=0.0)})
