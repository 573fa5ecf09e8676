"""A small, non-adversarial restorer: learnable Wiener deconvolution of features of the sensor image, then a
residual UNet, trained with the Charbonnier L1 loss (and optionally the FFT loss) alone.

    b^ = UNet(head(G_v(s, h))) + 1x1(G_v(s, h)),   G_v = FE + per-feature Wiener filter with the system OTF

It is the SGAN's middle and last stage without G1 and without critics: no adversarial training, no gradient
penalty, a fraction of the parameters, so it trains in minutes on a CPU. ``model=wiener_unet`` selects it; the
trainer, the evaluation and the co-design run it through the restorer interface (codesign/models/restorer.py).
This module is the whole plug-in: importing codesign.models registers its kind and its config node.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import torch
import torch.nn as nn

from codesign.config.store import register, spec_node
from codesign.errors import ConfigError, require_choice, require_number
from codesign.models import losses
from codesign.models.restorer import Restorer, TrainContext
from codesign.models.spec import network_name
from codesign.models.unet import UNetBody, make_head, zero_conv
from codesign.models.wiener import DeconvModule
from codesign.spec_base import SpecMixin

SIZES = {"tiny": (4, (8, 8)), "cpu": (16, (16, 32, 64)), "paper": (64, (64, 128, 256, 512))}


@dataclass(frozen=True)
class WienerUNetSpec(SpecMixin):
    """name: the network's name as configured (model=NAME), in the logs, metrics.json (network) and figure titles;
    null: wiener_unet. size: tiny | cpu | paper (stem width and UNet levels); fe_features / fe_kernel: the feature
    extractor;
    gamma_init: initial learned noise power of the Wiener filter; attention: efficient self-attention per level;
    l1, fft: weights of the Charbonnier L1 and the FFT loss; charbonnier_eps."""

    kind: str = "wiener_unet"
    name: str | None = None
    size: str = "cpu"
    fe_features: int = 8
    fe_kernel: int = 5
    gamma_init: float = 1e-2
    attention: bool = False
    l1: float = 1.0
    fft: float = 0.0
    charbonnier_eps: float = 1e-6
    prefix: str = field(default="model", compare=False, repr=False)

    def __post_init__(self) -> None:
        p = self.prefix
        object.__setattr__(self, "name", network_name(f"{p}.name", self.name, "wiener_unet"))
        require_choice(f"{p}.size", self.size, tuple(SIZES))
        require_number(f"{p}.fe_features", self.fe_features, lo=1, hi=1024, integer=True)
        require_number(f"{p}.fe_kernel", self.fe_kernel, lo=1, hi=15, integer=True)
        if self.fe_kernel % 2 == 0:
            raise ConfigError(f"{p}.fe_kernel", self.fe_kernel, "must be odd (same-size convolution)")
        require_number(f"{p}.gamma_init", self.gamma_init, lo=1e-7, hi=1e6)
        for key in ("l1", "fft"):
            require_number(f"{p}.{key}", getattr(self, key), lo=0)
        require_number(f"{p}.charbonnier_eps", self.charbonnier_eps, lo=0, lo_open=True, hi=1)
        if not isinstance(self.attention, bool):
            raise ConfigError(f"{p}.attention", self.attention, "must be true or false")


class _Refine(nn.Module):
    """head -> UNet body -> 1 channel, plus a 1x1 readout of the deconvolved features."""

    def __init__(self, spec: WienerUNetSpec):
        super().__init__()
        stem, widths = SIZES[spec.size]
        self.head = make_head(spec.fe_features, stem, 2)
        self.body = UNetBody(stem, widths, 1, "res", spec.attention, 8)
        self.skip = zero_conv(spec.fe_features, 1, 1)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.body(self.head(features)) + self.skip(features)


class WienerUNet(Restorer):
    """See the module docstring."""

    kind = "wiener_unet"
    method = "wiener_unet"

    def __init__(self, spec: WienerUNetSpec | None = None):
        super().__init__()
        self.spec = spec if spec is not None else WienerUNetSpec()
        self.gv = DeconvModule(self.spec.fe_features, self.spec.fe_kernel, self.spec.gamma_init)
        self.refine = _Refine(self.spec)

    @classmethod
    def from_config(cls, cfg: Mapping) -> "WienerUNet":
        """From a ``model`` block: every key a WienerUNetSpec field (no separate loss block)."""
        return cls(WienerUNetSpec.from_config(dict(cfg)))

    def generators(self) -> list[nn.Module]:
        """[G_v (features + learnable Wiener), the refining UNet]; no critics."""
        return [self.gv, self.refine]

    def forward_with(self, generators, sensor: torch.Tensor, otf: torch.Tensor) -> dict:
        """{"restored": (B, 1, P, P)}: the UNet's refinement of the Wiener-deconvolved features of ``sensor``
        (B, 1, P, P), ``otf`` (P, P // 2 + 1) on the same grid."""
        gv, refine = generators
        return {"restored": refine(gv(sensor, otf))}

    def generator_losses(self, batch: dict, out: dict, ctx: TrainContext) -> dict:
        """Charbonnier L1 (and the FFT loss when weighted) between the restoration and the scene over the whole
        padded canvas."""
        s = self.spec
        terms = {"rec2": losses.charbonnier(out["restored"], batch["scene"], s.charbonnier_eps)}
        total = s.l1 * terms["rec2"]
        if s.fft > 0:
            terms["fft"] = losses.fft_loss(out["restored"], batch["scene"])
            total = total + s.fft * terms["fft"]
        terms["generator_total"] = total
        return terms

    def summary(self) -> dict:
        """The network's name (model.name, default wiener_unet), variant "wiener_unet" and its size."""
        return {"network": self.spec.name, "variant": self.kind, "size": self.spec.size}

    def scalars(self) -> dict[str, float]:
        """Mean, min and max of G_v's learned Wiener noise powers gamma_i (``wiener/gamma_*``)."""
        gamma = self.gv.deconv.gamma.detach()
        return {"wiener/gamma_mean": float(gamma.mean()), "wiener/gamma_min": float(gamma.min()),
                "wiener/gamma_max": float(gamma.max())}

    def check_input_size(self, padded_size: int, key: str = "data.padded_size") -> None:
        """ConfigError naming ``key`` when ``padded_size`` < 2^levels of this size's UNet (tiny 4, cpu 8, paper 16)."""
        need = 2 ** len(SIZES[self.spec.size][1])
        if padded_size < need:
            raise ConfigError(key, padded_size, f"too small for model.size={self.spec.size}: the UNet's "
                              f"{need // 2}x downsampling needs padded_size >= {need}")


register("model", "wiener_unet", spec_node(WienerUNetSpec, name="wiener_unet"))
