"""Wiener deconvolution: the classical filter and the learnable feature-space module G_v = {FE, deconv}.

Both solve the L2-regularized least squares problem in closed form on the (circular) padded grid:
    x^ = F^-1{ Y conj(H) / (|H|^2 + nsr) }.
Classical: nsr is one constant (tuned). Learnable (Eq. Deconvolution): nsr_i = gamma_i / E|F_i|^2 per feature
and per image, with E|F_i|^2 the mean power of feature i (ortho FFT, so it equals the spatial mean of f_i^2 by
Parseval) and gamma_i > 0 a learned noise power. The filter is written as  Y conj(H) P / (|H|^2 P + gamma),
which is finite at zero feature power (P = 0 -> 0) and at OTF zeros (H = 0 -> 0) because gamma > 0.
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from codesign.models.blocks import conv_norm_act
from codesign.models.unet import residual_block


def wiener_filter(y: torch.Tensor, otf: torch.Tensor, power: torch.Tensor | float,
                  noise: torch.Tensor | float) -> torch.Tensor:
    """F^-1{ Y conj(H) P / (|H|^2 P + noise) } for y (..., H, W) and otf (H, W // 2 + 1).

    power, noise broadcast against (..., 1, 1); nsr = noise / power. Computed in float32 or wider. Where
    |H|^2 P + noise = 0 (noise 0 or underflowing, at an OTF zero or a zero-power input) the output is 0, the limit
    noise -> 0+: noise = 0 is the pseudo-inverse filter.
    """
    return _wiener_filters(y, otf, power, [noise])[0]


def _wiener_filters(y: torch.Tensor, otf: torch.Tensor, power, noises) -> list[torch.Tensor]:
    """The Wiener filter for each noise value, sharing one forward FFT of y."""
    h, w = y.shape[-2:]
    dtype = torch.promote_types(y.dtype, torch.float32)
    spec = torch.fft.rfft2(y.to(dtype), norm="ortho")
    otf = otf.to(device=spec.device, dtype=spec.dtype)
    num = spec * otf.conj() * power
    den = (otf.real**2 + otf.imag**2) * power
    out = []
    for n in noises:
        d = den + n
        # d = 0 only where |H|^2 P = 0 and the noise is 0, or so small that it underflows in float32 (nsr = 1e-300
        # is accepted, and is 0 in float32): the numerator Y conj(H) P is then exactly 0 as well, and the filter's
        # limit as the noise -> 0+ is 0 there, where the plain quotient gives 0 / 0 = NaN (and NaN gradients).
        # The real d divides the real and imaginary parts: complex / real promotes d to complex, whose division
        # forms 1 / d, which overflows float32 for d < 3e-39 (0 * inf = NaN at the OTF zeros, e.g. nsr = 1e-45).
        ok = d > 0
        d = torch.where(ok, d, torch.ones_like(d))
        q = torch.where(ok, torch.complex(num.real / d, num.imag / d), torch.zeros_like(num))
        out.append(torch.fft.irfft2(q, s=(h, w), norm="ortho").to(y.dtype))
    return out


def classical_wiener(y: torch.Tensor, otf: torch.Tensor, nsr: float) -> torch.Tensor:
    """Classical Wiener deconvolution with one noise-to-signal ratio (nsr > 0)."""
    return classical_wiener_sweep(y, otf, [nsr])[0]


def classical_wiener_sweep(y: torch.Tensor, otf: torch.Tensor, nsrs) -> list[torch.Tensor]:
    """classical_wiener(y, otf, k) for every k in ``nsrs`` (one forward FFT for all: for tuning)."""
    for k in nsrs:
        if not k > 0:
            raise ValueError(f"nsr must be > 0, got {k}")
    return _wiener_filters(y, otf, 1.0, nsrs)


class FeatureExtractor(nn.Module):
    """FE = CRRR16 with kernel 5 (supplement Sec. 2.2): N feature images of the pre-restored irradiance."""

    def __init__(self, in_channels: int = 1, features: int = 16, kernel: int = 5, residual_blocks: int = 3,
                 block: str = "res"):
        super().__init__()
        self.net = nn.Sequential(conv_norm_act(in_channels, features, kernel),
                                 *[residual_block(block, features, kernel) for _ in range(residual_blocks)])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, N, H, W) feature images of ``x`` (B, in_channels, H, W)."""
        return self.net(x)


class LearnableWiener(nn.Module):
    """deconv of Eq. (Deconvolution): each feature deconvolved with nsr_i = gamma_i / E|F_i|^2.

    gamma_i = softplus(rho_i) + gamma_min is kept positive; ``gamma`` reports it.
    """

    def __init__(self, features: int, gamma_init: float, gamma_min: float = 1e-8):
        super().__init__()
        if not gamma_init > gamma_min:
            raise ValueError(f"gamma_init must be > gamma_min ({gamma_min}), got {gamma_init}")
        g = gamma_init - gamma_min
        # inverse softplus, stable for small g
        self.rho = nn.Parameter(torch.full((features,), g + math.log(-math.expm1(-g))))
        self.gamma_min = gamma_min

    @property
    def gamma(self) -> torch.Tensor:
        """(N,) the learned noise powers gamma_i = softplus(rho_i) + gamma_min, with their graph."""
        return F.softplus(self.rho) + self.gamma_min

    def forward(self, f: torch.Tensor, otf: torch.Tensor) -> torch.Tensor:
        """Each feature of ``f`` (B, N, P, P) Wiener-deconvolved with ``otf`` (P, P // 2 + 1) at nsr_i =
        gamma_i / E|F_i|^2, in float32 at least (autocast off)."""
        # in float32 at least, whatever autocast does around it: the FFTs and the division by |H|^2 + nsr (OTF
        # zeros, nsr down to 1e-8) are not safe in bfloat16's 8-bit mantissa
        with torch.autocast(f.device.type, enabled=False):
            f = f.to(torch.promote_types(f.dtype, torch.float32))
            power = f.square().mean(dim=(-2, -1), keepdim=True)  # E|F_i|^2
            return wiener_filter(f, otf, power, self.gamma.view(1, -1, 1, 1))


class DeconvModule(nn.Module):
    """G_v = {FE, deconv}: features of the pre-restored irradiance, each deconvolved with the system OTF."""

    no_compile = True  # trainer.compile leaves it alone: its complex FFTs gain nothing from torch.compile

    def __init__(self, features: int, kernel: int, gamma_init: float, block: str = "res"):
        super().__init__()
        self.fe = FeatureExtractor(1, features, kernel, block=block)
        self.deconv = LearnableWiener(features, gamma_init)

    def forward(self, i_b: torch.Tensor, otf: torch.Tensor) -> torch.Tensor:
        """(B, N, P, P) deconvolved features of the pre-restored irradiance ``i_b`` (B, 1, P, P), float32 at least."""
        return self.deconv(self.fe(i_b), otf)
