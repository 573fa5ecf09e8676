"""PatchGAN critics (supplement Sec. 2.3): E64-E128-E256-E512 with kernel 4, then a 1-channel output conv.

As in pix2pix (which the paper cites for PatchGAN) the first three E blocks have stride 2 and the fourth stride
1, giving each output value a 70 x 70 receptive field (the "70 x 70 patch" of the supplement); the first block has
no normalization. LeakyReLU(0.2) instead of ReLU: dead units in a WGAN critic flatten the very gradients the
gradient penalty constrains. An attention block A follows every level. SGAN-F replaces the convolutions of the E
blocks by FFT-convolution (FTC) blocks. The critic returns its output map and the activation of every level
(for the multiscale feature-matching loss).
"""
from __future__ import annotations

from typing import Sequence

import torch
import torch.nn as nn

from codesign.models.blocks import EfficientAttention, FFTConvBlock, conv_norm_act


class PatchDiscriminator(nn.Module):
    def __init__(self, in_channels: int, widths: Sequence[int] = (64, 128, 256, 512), block: str = "conv",
                 attention: bool = True, *, key_channels: int):
        super().__init__()
        if block not in ("conv", "ftc"):
            raise ValueError(f"discriminator block must be conv or ftc, got {block!r}")
        levels = []
        cin = in_channels
        for i, w in enumerate(widths):
            stride = 2 if i < len(widths) - 1 else 1
            if block == "conv":
                layer = conv_norm_act(cin, w, 4, stride=stride, norm=i > 0, act="leaky_relu")
                if stride == 1:  # pix2pix padding 1 for the stride-1 layer too (output n - 1)
                    layer[0].padding = (1, 1)
            else:
                layer = FFTConvBlock(cin, w, stride=stride, norm=i > 0)
            att = EfficientAttention(w, key_channels) if attention else nn.Identity()
            levels.append(nn.Sequential(layer, att))
            cin = w
        self.levels = nn.ModuleList(levels)
        self.out = nn.Conv2d(cin, 1, 4, 1, 1)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """(the critic's score map (B, 1, h, w), one value per 70 x 70 patch; the activation of every level, for
        the feature-matching loss)."""
        feats = []
        for level in self.levels:
            x = level(x)
            feats.append(x)
        return self.out(x), feats


def receptive_field(levels: int) -> int:
    """Receptive field (pixels) of one output of a PatchDiscriminator with ``levels`` E blocks: kernel 4 everywhere,
    stride 2 for all but the last block, then the stride-1 output conv."""
    rf, jump = 1, 1
    strides = [2] * (levels - 1) + [1, 1]
    for s in strides:
        rf += 3 * jump
        jump *= s
    return rf
