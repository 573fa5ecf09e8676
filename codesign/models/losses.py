"""Training losses of the sandwich GAN (paper Sec. 4; weights in the supplement, "Hyper-parameters in Training").

Every function returns a scalar tensor. Sums over the two pyramid scales L = 0, 1 of the paper are the caller's
(one call per scale) except where a function takes per-scale lists (the adversarial terms and MDF). The lambda
weights are the caller's too.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import torch
import torch.nn as nn

from codesign.errors import ConfigError, require_choice, require_list, require_number
from codesign.models.vgg import ImageNetInput, extract, layer_index, load_vgg_features
from codesign.spec_base import SpecMixin

Tensors = torch.Tensor | Sequence[torch.Tensor]


def charbonnier(x: torch.Tensor, y: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Charbonnier L1 (Eq. RecLoss): mean of sqrt((x-y)^2 + eps) - sqrt(eps).

    Subtracting the constant sqrt(eps) makes the loss exactly 0 for identical inputs without changing any
    gradient. It is evaluated as d^2 / (sqrt(d^2 + eps) + sqrt(eps)), the same value without the cancellation of
    two nearly equal square roots. kornia's charbonnier_loss is this form with eps fixed to 1 (Barron's c = 1), so
    it would need inputs rescaled by 1/sqrt(eps); plain torch is clearer.
    """
    d2 = (x - y).square()
    root_eps = eps ** 0.5
    return (d2 / ((d2 + eps).sqrt() + root_eps)).mean()


def _as_list(t: Tensors) -> list[torch.Tensor]:
    return [t] if isinstance(t, torch.Tensor) else list(t)


def critic_loss(d_real: Tensors, d_fake: Tensors) -> torch.Tensor:
    """WGAN critic loss to minimize: sum over scales of mean(D(fake)) - mean(D(real)) (no GP, no lambda)."""
    real, fake = _as_list(d_real), _as_list(d_fake)
    if len(real) != len(fake) or not real:
        raise ValueError(f"need as many real as fake critic outputs (>= 1), got {len(real)} and {len(fake)}")
    return sum(f.mean() - r.mean() for r, f in zip(real, fake))


def generator_adv_loss(d_fake: Tensors) -> torch.Tensor:
    """WGAN generator loss: -sum over scales of mean(D(fake))."""
    return -sum(f.mean() for f in _as_list(d_fake))


def gradient_penalty(critic: Callable, real: torch.Tensor, fake: torch.Tensor, cond: torch.Tensor | None = None,
                     generator: torch.Generator | None = None, eps: torch.Tensor | None = None) -> torch.Tensor:
    """WGAN-GP (Gulrajani 2017): mean over samples of (||grad_x~ D(x~)||_2 - 1)^2, without lambda_GP.

    x~ = eps * real + (1 - eps) * fake with eps ~ U(0, 1) per sample (``generator`` for reproducible draws; it must
    live on the device of ``real``; or ``eps`` given, shape (B,)). With ``cond`` the critic sees
    torch.cat([cond, x~], 1) and the gradient is taken w.r.t. x~ only. real, fake and cond are detached: the penalty
    trains the critic only. A critic returning (output, features) is accepted.
    The critic value of a sample is the mean of its output map (PatchGAN patch
    scores), the reduction critic_loss uses, so the Lipschitz constraint is on the function whose expectation the
    WGAN loss estimates (summing the patch map instead would ask each patch for 1/num_patches). Per-sample
    gradients assume the critic mixes no samples (no batch norm), as WGAN-GP requires anyway. create_graph=True,
    so the result can be backpropagated into the critic's parameters.
    """
    real, fake = real.detach(), fake.detach()
    if real.shape != fake.shape:
        raise ValueError(f"real and fake shapes differ: {tuple(real.shape)} vs {tuple(fake.shape)}")
    b = real.shape[0]
    if eps is None:
        eps = torch.rand((b,), generator=generator, device=real.device, dtype=real.dtype)
    elif eps.shape != (b,):
        raise ValueError(f"eps must have shape ({b},), got {tuple(eps.shape)}")
    eps = eps.reshape((b,) + (1,) * (real.ndim - 1))
    x = (eps * real + (1 - eps) * fake).requires_grad_(True)
    inp = x if cond is None else torch.cat([cond.detach(), x], 1)
    out = critic(inp)
    if isinstance(out, (tuple, list)):
        out = out[0]
    per_sample = out.reshape(b, -1).mean(1)
    (grad,) = torch.autograd.grad(per_sample.sum(), x, create_graph=True)
    return (grad.reshape(b, -1).norm(2, dim=1) - 1).square().mean()


def feature_matching_loss(feats_real, feats_fake) -> torch.Tensor:
    """Multiscale discriminator feature matching (MDF, Eq. FMLoss): sum over scales L of
    (1 / T_L) * sum over layers t of mean |D_t(real) - D_t(fake)|, with the real features detached.

    Arguments are lists (one per scale) of lists (one per layer) of tensors; a single list of tensors counts as
    one scale. Which layers to pass (e.g. the critic's intermediate activations, without the output map) is the
    caller's choice; T_L is the number passed for scale L.
    """
    if feats_real and isinstance(feats_real[0], torch.Tensor):
        feats_real, feats_fake = [feats_real], [feats_fake]
    if len(feats_real) != len(feats_fake):
        raise ValueError(f"real and fake have {len(feats_real)} and {len(feats_fake)} scales")
    total = 0.0
    for r_layers, f_layers in zip(feats_real, feats_fake):
        if len(r_layers) != len(f_layers) or not r_layers:
            raise ValueError(f"real and fake have {len(r_layers)} and {len(f_layers)} layers (need >= 1, equal)")
        total = total + sum((r.detach() - f).abs().mean() for r, f in zip(r_layers, f_layers)) / len(r_layers)
    return total


def fft_loss(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """FFT loss (Eq. FFTLoss): mean over coefficients of |F(x) - F(y)|, F = rfft2 over the last two axes.

    norm="ortho" makes F unitary (Parseval: sum |F(e)|^2 = sum |e|^2), so the size of a broadband error's
    coefficients, and with it the weight lambda_FFT that balances this loss against the pixel losses, does not
    depend on the image size (the default unnormalized transform grows them by sqrt(H W)). The modulus of the
    complex difference is taken (not |Re| + |Im|). For a constant offset c on an H x W image only the DC
    coefficient is nonzero, |c| sqrt(H W), so the loss is |c| sqrt(H W) / (H (W // 2 + 1)).
    """
    d = torch.fft.rfft2(x, norm="ortho") - torch.fft.rfft2(y, norm="ortho")
    return d.abs().mean()


VGG19_DEFAULT_LAYERS = ("relu1_2", "relu2_2", "relu3_4", "relu4_4", "relu5_4")  # indices 3, 8, 17, 26, 35


class VGGPerceptualLoss(nn.Module):
    """VGG loss (Eq. VGGLoss) for one scale: (1/T_V) sum_t mean |V_t(x) - V_t(y)| over the chosen VGG19 layers.

    Inputs are (B,1,H,W) grayscale in [0,1], replicated to 3 channels and ImageNet-normalized; the network runs only
    up to the deepest requested layer. ``layers`` are torchvision indices or names (``"relu3_4"``). The VGG weights
    are frozen (requires_grad False, always eval mode) but remain parameters of this module: a checkpoint of a
    module that holds this one would carry the VGG19 weights (~80 MB); keep the loss outside saved modules.
    """

    def __init__(self, features: nn.Sequential, layers: Sequence[int | str] = VGG19_DEFAULT_LAYERS,
                 kind: str = "vgg19"):
        super().__init__()
        self.indices = sorted({layer_index(kind, layer) for layer in layers})
        if not self.indices or self.indices[-1] >= len(features):
            raise ValueError(f"VGGPerceptualLoss needs >= 1 layer within the {len(features)} given modules, got "
                             f"{list(layers)}")
        self.features = features[: max(self.indices) + 1]
        self.features.requires_grad_(False)
        self.prep = ImageNetInput()
        self.train(False)

    def train(self, mode: bool = True):
        """Set this module's mode as nn.Module.train does, but keep the frozen VGG features in eval mode."""
        super().train(mode)
        self.features.eval()  # frozen feature extractor; VGG has no dropout/BN here, but keep it explicit
        return self

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Scalar loss between ``x`` and ``y`` (B,1,H,W, same shape): the mean over layers of mean |V_t(x) - V_t(y)|,
        both through one VGG pass; ValueError if the shapes differ."""
        if x.shape != y.shape:
            raise ValueError(f"shapes differ: {tuple(x.shape)} vs {tuple(y.shape)}")
        b = x.shape[0]
        feats = extract(self.features, self.prep(torch.cat([x, y], 0)), self.indices)  # one pass for both
        return sum((f[:b] - f[b:]).abs().mean() for f in feats) / len(feats)


def build_vgg_loss(weights_path, layers: Sequence[int | str] | None = None) -> tuple[VGGPerceptualLoss | None, str]:
    """(loss module, status): (None, "off: ...") without a path; otherwise VGG19 loaded from ``weights_path`` (a bad
    file raises ConfigError naming model.loss.vgg_weights) and (module, "on: <path>")."""
    if weights_path is None or str(weights_path) == "":
        return None, "off: no VGG19 weights configured (model.loss.vgg_weights)"
    features = load_vgg_features("vgg19", weights_path, key="model.loss.vgg_weights")
    return VGGPerceptualLoss(features, VGG19_DEFAULT_LAYERS if layers is None else layers), f"on: {weights_path}"


LOSS_REGIONS = ("canvas", "field")


@dataclass(frozen=True)
class LossWeights(SpecMixin):
    """Loss weights of one SGAN variant (supplement, Table "Values of Hyperparameters in Model Training").

    l1_stage1: Charbonnier L1 on I_b (s1); l1_stage2: Charbonnier L1 on both scales of b (s2); mdf: multiscale
    discriminator feature matching; vgg: VGG19 perceptual (needs vgg_weights); fft: FFT loss; adv: lambda_ADV of
    both GANs; gp: lambda_GP. charbonnier_eps: the epsilon of sqrt(|x|^2 + eps). region: where the terms that
    compare with a target (L1 on I_b and on b, VGG, FFT) are taken: "canvas", the whole padded grid (the paper's
    images are the padded ones, so its networks also learn to outpaint the scene beyond the sensor's field), or
    "field", the sensor's field alone, where every method is scored; the critics judge the canvas either way.
    """

    l1_stage1: float = 200.0
    l1_stage2: float = 50.0
    mdf: float = 50.0
    vgg: float = 0.0
    fft: float = 0.0
    adv: float = 1.0
    gp: float = 10.0
    charbonnier_eps: float = 1e-6
    vgg_weights: str | None = None
    vgg_layers: tuple = (3, 8, 17, 26, 35)
    region: str = "canvas"
    prefix: str = field(default="model.loss", compare=False, repr=False)

    def __post_init__(self) -> None:
        for k in ("l1_stage1", "l1_stage2", "mdf", "vgg", "fft", "adv", "gp"):
            require_number(f"{self.prefix}.{k}", getattr(self, k), lo=0)
        require_number(f"{self.prefix}.charbonnier_eps", self.charbonnier_eps, lo=0, lo_open=True, hi=1)
        require_choice(f"{self.prefix}.region", self.region, LOSS_REGIONS)
        layers = require_list(f"{self.prefix}.vgg_layers", self.vgg_layers, "must be a list of VGG19 feature layers "
                              "(indices 0..36 or names such as relu3_4)")
        for i, layer in enumerate(layers):  # refused now, not when the VGG weights are loaded after the data
            try:
                layer_index("vgg19", layer)
            except ConfigError as err:
                raise ConfigError(f"{self.prefix}.vgg_layers[{i}]", layer, err.allowed) from None
        object.__setattr__(self, "vgg_layers", tuple(layers))
        if self.mdf > 0 and self.adv == 0:
            raise ConfigError(f"{self.prefix}.mdf", self.mdf, "needs model.loss.adv > 0: the critics whose features "
                              "it matches are trained only by the adversarial term")
