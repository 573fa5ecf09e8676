"""The sandwich GAN, Eq. (image_restore_model):  b^ = G2(G_v(G1(s, x, y), h)).

  G1  residual UNet on (s, x, y) -> I_b^ (pre-restored irradiance: laser inpainted, border outpainted, denoised)
  G_v FE (CRRR16, kernel 5) -> learnable Wiener deconvolution of each feature with the system OTF
  G2  residual UNet on two scales: per-scale input layers, shared body; coarse = features downsampled 2x with
      antialiased bicubic; outputs [b^0 (coarse), b^1 (fine)]
  D1  conditional PatchGAN on (s, x, y, I_b);  D2 = {D2^0, D2^1} PatchGANs on b^L
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from codesign.models.discriminators import PatchDiscriminator
from codesign.models.spec import ModelSpec
from codesign.models.unet import ResUNet, UNetBody, make_head, zero_conv
from codesign.models.wiener import DeconvModule


def coordinates(like: torch.Tensor) -> torch.Tensor:
    """(B, 2, H, W) coordinate channels (x, y) in [-1, 1] over the padded grid."""
    b, _, h, w = like.shape
    ys = torch.linspace(-1, 1, h, device=like.device, dtype=like.dtype)
    xs = torch.linspace(-1, 1, w, device=like.device, dtype=like.dtype)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([gx, gy])[None].expand(b, -1, -1, -1)


def downsample2(x: torch.Tensor) -> torch.Tensor:
    """Half resolution by antialiased bicubic interpolation (features and targets alike)."""
    h, w = x.shape[-2:]
    return F.interpolate(x, size=(h // 2, w // 2), mode="bicubic", antialias=True, align_corners=False)


def pyramid(x: torch.Tensor) -> list[torch.Tensor]:
    """[coarse, fine] targets for G2."""
    return [downsample2(x), x]


def pre_restore(g1: nn.Module, sensor: torch.Tensor, residual: bool) -> torch.Tensor:
    out = g1(torch.cat([sensor, coordinates(sensor)], 1))
    return sensor + out if residual else out


def sandwich(generators, sensor: torch.Tensor, otf: torch.Tensor, g1_residual: bool) -> dict:
    """G2(G_v(G1(s, x, y), h)) with the given (g1, gv, g2) modules (the model's own, or e.g. EMA copies)."""
    p = sensor.shape[-1]
    if sensor.shape[-2] != p or tuple(otf.shape[-2:]) != (p, p // 2 + 1):
        raise ValueError(f"sensor must be (B, 1, P, P) with an OTF of shape (P, P // 2 + 1); got sensor "
                         f"{tuple(sensor.shape)} and OTF {tuple(otf.shape)}")
    g1, gv, g2 = generators
    i_b = pre_restore(g1, sensor, g1_residual)
    features = gv(i_b, otf)
    return {"i_b": i_b, "features": features, "b": g2(features)}


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

    def _scale(self, head: nn.Module, x: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        out = self.body(head(x))
        return out if self.skip is None else out + self.skip(features)

    def forward(self, features: torch.Tensor) -> list[torch.Tensor]:
        small = downsample2(features)
        coarse = self._scale(self.heads[0], small, small)
        fine_in = features
        if self.coarse_to_fine:
            up = F.interpolate(coarse, size=features.shape[-2:], mode="bicubic", align_corners=False)
            fine_in = torch.cat([features, up], 1)
        return [coarse, self._scale(self.heads[1], fine_in, features)]


class SGAN(nn.Module):
    def __init__(self, spec: ModelSpec):
        super().__init__()
        self.spec = spec
        g, d = spec.generator_block, spec.critic_block
        self.g1 = ResUNet(3, 1, spec.stem_width, spec.widths, g, spec.attention, spec.key_channels)
        self.gv = DeconvModule(spec.fe_features, spec.fe_kernel, spec.gamma_init)
        self.g2 = Refiner(spec)
        self.d1 = PatchDiscriminator(4, spec.d_widths, d, spec.attention, spec.key_channels)
        self.d2 = nn.ModuleList([PatchDiscriminator(1, spec.d_widths, d, spec.attention, spec.key_channels)
                                 for _ in range(2)])

    def generators(self) -> list[nn.Module]:
        return [self.g1, self.gv, self.g2]

    def discriminators(self) -> list[nn.Module]:
        return [self.d1, self.d2]

    def pre_restore(self, sensor: torch.Tensor) -> torch.Tensor:
        """G1: (B, 1, P, P) normalized sensor image -> I_b^ (B, 1, P, P)."""
        return pre_restore(self.g1, sensor, self.spec.g1_residual)

    def forward(self, sensor: torch.Tensor, otf: torch.Tensor) -> dict:
        """sensor (B, 1, P, P); otf (P, P // 2 + 1) of the system PSF kernel at the network pitch.

        Returns i_b (B,1,P,P), features (B,N,P,P) after deconvolution, b = [b^0 (B,1,P/2,P/2), b^1 (B,1,P,P)].
        """
        return sandwich(self.generators(), sensor, otf, self.spec.g1_residual)

    def critic1(self, sensor: torch.Tensor, i_b: torch.Tensor):
        """D1(s, x, y, I_b) -> (patch scores, level features)."""
        return self.d1(torch.cat([sensor, coordinates(sensor), i_b], 1))

    def condition1(self, sensor: torch.Tensor) -> torch.Tensor:
        """The conditioning channels of D1: (s, x, y)."""
        return torch.cat([sensor, coordinates(sensor)], 1)


def parameter_count(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
