"""The residual UNet of G1 and G2 (supplement Sec. 2.1).

  encoder  C - ERRA w1 - ERRA w2 - ... - ERRA wn           (paper: C7, then 64,128,256,512,512,512,512)
  decoder  DRRA wn - ... - DRRA w1                         (paper: 512,512,512,512,256,128,64)
  output   Conv k7 on [decoder output, C output] -> out channels

Each decoder block takes the previous decoder output concatenated with the encoder activation of the same
resolution (the skip from layer i to layer n - i) and doubles the resolution. SGAN-F swaps R for RFT blocks.
The input layers (``head``) are separate modules so that G2 can keep one head per scale and share the rest.
"""
from __future__ import annotations

from typing import Sequence

import torch
import torch.nn as nn

from codesign.models.blocks import (
    EfficientAttention,
    InstanceNorm,
    ResBlock,
    ResFFTBlock,
    conv_norm_act,
    match_size,
)


def residual_block(kind: str, channels: int, kernel: int = 3) -> nn.Module:
    """A residual block of the given kind: res (ResBlock) or rft (ResFFTBlock, SGAN-F)."""
    if kind == "res":
        return ResBlock(channels, kernel)
    if kind == "rft":
        return ResFFTBlock(channels, kernel)
    raise ValueError(f"block must be res or rft, got {kind!r}")


class Stage(nn.Module):
    """ERRA / DRRA: a resampling block (E: strided conv; D: transposed conv), two residual blocks, attention."""

    def __init__(self, cin: int, cout: int, up: bool, block: str, attention: bool, key_channels: int,
                 residual_blocks: int = 2):
        super().__init__()
        if up:
            self.resample = nn.Sequential(nn.ConvTranspose2d(cin, cout, 4, 2, 1), InstanceNorm(cout),
                                          nn.ReLU(inplace=True))
        else:
            self.resample = conv_norm_act(cin, cout, 4, stride=2)
        self.residual = nn.Sequential(*[residual_block(block, cout) for _ in range(residual_blocks)])
        self.attention = EfficientAttention(cout, key_channels) if attention else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """attention(residual(resample(x))): (B, cout, H', W') at half (E) or twice (D) the resolution of ``x``."""
        return self.attention(self.residual(self.resample(x)))


class UNetBody(nn.Module):
    """Everything of the residual UNet after its input layers: encoder stages, decoder stages, output conv.

    forward(stem) takes the head's output (B, stem_width, H, W) and returns (B, out_channels, H, W); H and W need
    not be multiples of 2^depth (decoder outputs are padded to the skip's size).
    """

    def __init__(self, stem_width: int, widths: Sequence[int], out_channels: int, block: str, attention: bool,
                 key_channels: int, residual_blocks: int = 2):
        super().__init__()
        widths = list(widths)
        ins = [stem_width] + widths[:-1]
        self.encoder = nn.ModuleList(Stage(ins[i], widths[i], False, block, attention, key_channels,
                                           residual_blocks) for i in range(len(widths)))
        # decoder block j (deepest first) mirrors encoder stage j: it outputs widths[j] at stage j's input
        # resolution, from the previous decoder output concatenated with encoder stage j's activation
        n = len(widths)
        self.decoder = nn.ModuleList(
            Stage(widths[j] + (widths[j + 1] if j < n - 1 else 0), widths[j], True, block, attention,
                  key_channels, residual_blocks) for j in reversed(range(n)))
        self.out = zero_conv(widths[0] + stem_width, out_channels, 7)

    def forward(self, stem: torch.Tensor) -> torch.Tensor:
        """(B, out_channels, H, W) from the head's output ``stem`` (B, stem_width, H, W), skips concatenated."""
        skips = [stem]
        x = stem
        for stage in self.encoder:
            x = stage(x)
            skips.append(x)
        x = skips.pop()
        for i, stage in enumerate(self.decoder):
            if i > 0:
                x = torch.cat([x, skips.pop()], 1)
            x = match_size(stage(x), skips[-1])
        return self.out(torch.cat([x, skips.pop()], 1))


class ResUNet(nn.Module):
    """G1 (and the single-scale G2): head C (kernel 7) + UNetBody."""

    def __init__(self, in_channels: int, out_channels: int, stem_width: int, widths: Sequence[int],
                 block: str = "res", attention: bool = True, *, key_channels: int, head_layers: int = 1):
        super().__init__()
        self.head = make_head(in_channels, stem_width, head_layers)
        self.body = UNetBody(stem_width, widths, out_channels, block, attention, key_channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """body(head(x)): (B, out_channels, H, W) for ``x`` (B, in_channels, H, W)."""
        return self.body(self.head(x))


def zero_conv(cin: int, cout: int, kernel: int) -> nn.Conv2d:
    """An output convolution that starts at zero (kept so by the trainer's init): the generator starts from a flat
    image (plus its skip), instead of from the std ~0.6 noise an orthogonal output layer produces, which L1
    losses then take thousands of steps to remove."""
    conv = nn.Conv2d(cin, cout, kernel, 1, kernel // 2)
    nn.init.zeros_(conv.weight)
    nn.init.zeros_(conv.bias)
    conv.zero_init = True
    return conv


def make_head(in_channels: int, width: int, layers: int) -> nn.Sequential:
    """Input layers: C with kernel 7, then (layers - 1) C blocks with kernel 3."""
    mods = [conv_norm_act(in_channels, width, 7)]
    mods += [conv_norm_act(width, width, 3) for _ in range(layers - 1)]
    return nn.Sequential(*mods)
