"""The building blocks of the supplement (Sec. 2, "Net Architecture"), named as there:

  C  Conv-InstanceNorm-ReLU, stride 1                 E  Conv-InstanceNorm-ReLU, stride 2 (kernel 4)
  R  two Conv-IN-ReLU layers plus the identity        D  ConvTranspose-IN-ReLU, stride 2 (kernel 4)
  A  efficient self-attention (four 1x1 convolutions: Q, K, V and the zero-initialized output R)
  RFT residual FFT block (SGAN-F): identity + spatial 3x3 branch + 1x1 convolutions on rfft2's real/imag parts
  FTC FFT-convolution block (SGAN-F discriminators): strided conv plus a downsampled spectral branch
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F


class InstanceNorm(nn.InstanceNorm2d):
    """Affine instance norm that passes a 1x1 feature map through unchanged.

    Why: the deepest level of a 7-level UNet on the coarse G2 scale (192 px) is 1x1, where instance statistics
    are undefined (torch raises in training); normalizing a single value would erase it anyway.
    """

    def __init__(self, channels: int):
        super().__init__(channels, affine=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Instance-normalized ``x`` (B, C, H, W), or ``x`` itself where the map is 1x1."""
        if x.shape[-1] * x.shape[-2] == 1:
            return x
        return super().forward(x)


def conv_norm_act(cin: int, cout: int, kernel: int, stride: int = 1, norm: bool = True,
                  act: str = "relu") -> nn.Sequential:
    """Conv2D-InstanceNorm-activation; 'same' padding for stride 1, halving (k=4, p=1) for stride 2."""
    pad = (kernel - 1) // 2 if stride == 1 else (kernel - stride) // 2
    layers: list[nn.Module] = [nn.Conv2d(cin, cout, kernel, stride, pad, padding_mode="zeros")]
    if norm:
        layers.append(InstanceNorm(cout))
    layers.append(activation(act))
    return nn.Sequential(*layers)


def activation(name: str) -> nn.Module:
    """The in-place activation named ``name``: ``relu`` (generators) or ``leaky_relu`` with slope 0.2 (critics)."""
    if name == "relu":
        return nn.ReLU(inplace=True)
    if name == "leaky_relu":
        return nn.LeakyReLU(0.2, inplace=True)
    raise ValueError(f"activation must be relu or leaky_relu, got {name!r}")


def conv_pair(channels: int, kernel: int) -> nn.Sequential:
    """Conv-IN-ReLU-Conv-IN at constant width: the body of R and the spatial branch of RFT."""
    p = kernel // 2
    return nn.Sequential(nn.Conv2d(channels, channels, kernel, 1, p), InstanceNorm(channels), nn.ReLU(inplace=True),
                         nn.Conv2d(channels, channels, kernel, 1, p), InstanceNorm(channels))


class ResBlock(nn.Module):
    """R: x + [Conv-IN-ReLU, Conv-IN](x), then ReLU (He et al. 2016, as the supplement's residual block)."""

    def __init__(self, channels: int, kernel: int = 3):
        super().__init__()
        self.body = conv_pair(channels, kernel)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """ReLU(x + body(x)), the same shape as ``x``."""
        return F.relu(x + self.body(x))


class SpectralBranch(nn.Module):
    """1x1 convolutions on the concatenated real and imaginary parts of rfft2(x) (a per-frequency linear map
    shared across frequencies), back through irfft2. Global receptive field at the cost of one FFT pair."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(2 * cin, 2 * cout, 1), nn.ReLU(inplace=True),
                                  nn.Conv2d(2 * cout, 2 * cout, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The spectral map of ``x`` (B, cin, H, W) as (B, cout, H, W) in ``x``'s dtype (FFTs in float32 at least)."""
        h, w = x.shape[-2:]
        # FFTs in float32 at least: half-precision rfft2 needs power-of-two sizes and loses the small coefficients
        wide = torch.promote_types(x.dtype, torch.float32)
        spec = torch.fft.rfft2(x.to(wide), norm="ortho")
        y = self.body(torch.cat([spec.real, spec.imag], 1).to(x.dtype)).to(wide)
        re, im = y.chunk(2, dim=1)
        return torch.fft.irfft2(torch.complex(re, im), s=(h, w), norm="ortho").to(x.dtype)


class ResFFTBlock(nn.Module):
    """RFT (Xint et al. 2023, DeepRFT): x + spatial(x) + spectral(x), then ReLU; replaces R in SGAN-F."""

    def __init__(self, channels: int, kernel: int = 3):
        super().__init__()
        self.spatial = conv_pair(channels, kernel)
        self.spectral = SpectralBranch(channels, channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """ReLU(x + spatial(x) + spectral(x)), the same shape as ``x``."""
        return F.relu(x + self.spatial(x) + self.spectral(x))


class FFTConvBlock(nn.Module):
    """FTC: a strided Conv(k4, s2) plus a spectral branch (1x1 convs on rfft2, average-pooled to the same grid),
    then InstanceNorm and the activation. Replaces the discriminators' E blocks in SGAN-F."""

    def __init__(self, cin: int, cout: int, stride: int = 2, norm: bool = True, act: str = "leaky_relu"):
        super().__init__()
        self.stride = stride
        self.conv = nn.Conv2d(cin, cout, 4, stride, 1)  # as the conv PatchGAN's layers (pix2pix padding)
        self.spectral = SpectralBranch(cin, cout)
        self.norm = InstanceNorm(cout) if norm else nn.Identity()
        self.act = activation(act)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """act(norm(conv(x) + spectral(x))): (B, cout, H', W') on the strided conv's grid (the spectral branch
        average-pooled by 2 for stride 2 and cropped to it)."""
        y = self.conv(x)
        s = self.spectral(x)
        if self.stride == 2:
            s = F.avg_pool2d(s, 2)
        return self.act(self.norm(y + s[..., : y.shape[-2], : y.shape[-1]]))


class EfficientAttention(nn.Module):
    """A: efficient self-attention with linear complexity (Shen et al. 2021, Eq. EffAttn of the paper).

    Q = M1 f, K = M2 f (d_k channels), V = M3 f (C channels). Keys are normalized by a softmax over positions,
    queries by a softmax over channels; E = softmax_rows(Q) [softmax_cols(K)^T V] costs O(d_k C N) instead of
    O(N^2). Output f + R(E), R a 1x1 convolution initialized to zero so that global context is learned gradually.
    """

    def __init__(self, channels: int, key_channels: int):
        super().__init__()
        self.query = nn.Conv2d(channels, key_channels, 1)
        self.key = nn.Conv2d(channels, key_channels, 1)
        self.value = nn.Conv2d(channels, channels, 1)
        self.proj = nn.Conv2d(channels, channels, 1)
        nn.init.zeros_(self.proj.weight)
        nn.init.zeros_(self.proj.bias)
        self.proj.zero_init = True  # the trainer's orthogonal init leaves it at zero

    def attend(self, x: torch.Tensor) -> torch.Tensor:
        """E(Q, K, V) as (B, C, H, W), before the output projection."""
        b, c, h, w = x.shape
        q = self.query(x).flatten(2).softmax(dim=1)           # (B, d_k, N): over channels
        k = self.key(x).flatten(2).softmax(dim=2)             # (B, d_k, N): over positions
        v = self.value(x).flatten(2)                          # (B, C, N)
        context = torch.bmm(k, v.transpose(1, 2))             # (B, d_k, C)
        return torch.bmm(context.transpose(1, 2), q).view(b, c, h, w)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """f + R(E): ``x`` plus the projected attention, (B, C, H, W); equal to ``x`` at initialization."""
        return x + self.proj(self.attend(x))


def match_size(x: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Zero-pad or crop x (bottom/right) to ref's spatial size: odd sizes lose a row on the way down."""
    dh, dw = ref.shape[-2] - x.shape[-2], ref.shape[-1] - x.shape[-1]
    if dh == 0 and dw == 0:
        return x
    return F.pad(x, (0, dw, 0, dh))
