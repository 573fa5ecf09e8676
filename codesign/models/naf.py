"""A light, fully local NAFNet-style U-Net (Chen et al. 2022, "Simple Baselines for Image Restoration"): gated blocks
with a per-pixel LayerNorm, no nonlinear activation but the simple gate, strong per FLOP on a CPU.

One departure from NAFNet, on purpose: no simplified channel attention (its global average pool). Every operation
here sees a bounded neighbourhood, so the network's output at a pixel does not depend on the size of the image it is
given, and a large capture can be decoded in overlapping tiles with the same result as whole (WienerNAF.restore_tiled).
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F


class LayerNorm2d(nn.Module):
    """LayerNorm over the channels of each pixel of a (B, C, H, W) map, with a per-channel scale and shift."""

    def __init__(self, channels: int, eps: float = 1e-6):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` (B, C, H, W) normalized over C at each pixel, then scaled and shifted per channel."""
        mu = x.mean(1, keepdim=True)
        var = (x - mu).square().mean(1, keepdim=True)
        return (x - mu) * torch.rsqrt(var + self.eps) * self.weight[:, None, None] + self.bias[:, None, None]


def simple_gate(x: torch.Tensor) -> torch.Tensor:
    """NAFNet's SimpleGate: the channels split in two halves, multiplied."""
    a, b = x.chunk(2, dim=1)
    return a * b


class NAFBlock(nn.Module):
    """x + beta * [LN, 1x1 (2c), depthwise 3x3, gate, 1x1](x), then y + gamma * [LN, 1x1 (2c), gate, 1x1](y).

    beta and gamma start at zero, so that a fresh block is the identity and a deep stack trains from the first step.
    """

    def __init__(self, c: int):
        super().__init__()
        self.norm1, self.norm2 = LayerNorm2d(c), LayerNorm2d(c)
        self.expand = nn.Conv2d(c, 2 * c, 1)
        self.depthwise = nn.Conv2d(2 * c, 2 * c, 3, padding=1, groups=2 * c)
        self.project = nn.Conv2d(c, c, 1)
        self.ffn_in = nn.Conv2d(c, 2 * c, 1)
        self.ffn_out = nn.Conv2d(c, c, 1)
        self.beta = nn.Parameter(torch.zeros(1, c, 1, 1))
        self.gamma = nn.Parameter(torch.zeros(1, c, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The block's output, the shape of ``x`` (B, c, H, W): the gated branch, then the gated feed-forward."""
        y = x + self.beta * self.project(simple_gate(self.depthwise(self.expand(self.norm1(x)))))
        return y + self.gamma * self.ffn_out(simple_gate(self.ffn_in(self.norm2(y))))


class NAFUNet(nn.Module):
    """in_channels -> width (3x3) -> encoder levels (NAF blocks, then a 2x2 stride-2 conv doubling the width) ->
    middle blocks -> decoder levels (1x1 conv + pixel shuffle halving the width, skip added, NAF blocks) ->
    out_channels (3x3, zero-initialized: a fresh network adds nothing to what it corrects).

    Any H, W: padded by replication to a multiple of 2^levels inside, cropped back.
    """

    def __init__(self, in_channels: int, out_channels: int, width: int, encoder: tuple[int, ...], middle: int,
                 decoder: tuple[int, ...]):
        super().__init__()
        if len(encoder) != len(decoder):
            raise ValueError(f"encoder and decoder need as many levels, got {encoder} and {decoder}")
        self.intro = nn.Conv2d(in_channels, width, 3, padding=1)
        self.encoders, self.downs, self.ups, self.decoders = (nn.ModuleList() for _ in range(4))
        c = width
        for n in encoder:
            self.encoders.append(nn.Sequential(*[NAFBlock(c) for _ in range(n)]))
            self.downs.append(nn.Conv2d(c, 2 * c, 2, stride=2))
            c *= 2
        self.middle = nn.Sequential(*[NAFBlock(c) for _ in range(middle)])
        for n in decoder:
            self.ups.append(nn.Sequential(nn.Conv2d(c, 2 * c, 1, bias=False), nn.PixelShuffle(2)))
            c //= 2
            self.decoders.append(nn.Sequential(*[NAFBlock(c) for _ in range(n)]))
        self.outro = nn.Conv2d(width, out_channels, 3, padding=1)
        nn.init.zeros_(self.outro.weight)
        nn.init.zeros_(self.outro.bias)
        self.outro.zero_init = True  # kept at zero by the trainer's init (codesign/models/unet.py zero_conv)
        self.multiple = 2 ** len(encoder)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, out_channels, H, W) for ``x`` (B, in_channels, H, W) of any H, W (replicate-padded to a multiple of
        2^levels inside, cropped back)."""
        h, w = x.shape[-2:]
        ph, pw = -h % self.multiple, -w % self.multiple
        if ph or pw:
            x = F.pad(x, (0, pw, 0, ph), mode="replicate")
        y = self.intro(x)
        skips = []
        for enc, down in zip(self.encoders, self.downs):
            y = enc(y)
            skips.append(y)
            y = down(y)
        y = self.middle(y)
        for up, dec, skip in zip(self.ups, self.decoders, reversed(skips)):
            y = dec(up(y) + skip)
        return self.outro(y)[..., :h, :w]

    @property
    def reach(self) -> int:
        """Receptive-field radius in input pixels (an upper bound): what an overlapping tile must add each side."""
        r, scale = 1, 1  # intro 3x3
        for enc in self.encoders:
            r += len(enc) * scale + scale  # a depthwise 3x3 per block; the 2x2 stride-2 conv
            scale *= 2
        r += len(self.middle) * scale
        for dec in self.decoders:
            r += scale  # the pixel shuffle spreads a coarse pixel over its 2 x 2 fine ones
            scale //= 2
            r += len(dec) * scale
        return r + 1  # outro 3x3
