"""WienerNAF: one restorer for every mask, conditioned on the system's OTF (``model=wiener_naf``).

    b^ = base + NAF-UNet(filled, saturated, halo, bank, deconvolved features)

It takes the capture and the OTF of the mask it came through (the PSF integrated over the network pixel, on the
capture's padded grid), so the mask is an input, not something learned into the weights:

- filled: the capture with its saturated pixels (the laser's footprint) and the padding around the sensor's field
  replaced by a smooth continuation of the measured pixels (push-pull, codesign/models/fill.py);
- saturated: where the sensor clipped; halo: where the laser's light lies, the PSF spread over the saturated pixels
  (codesign/models/sandwich.py halo_map): how one network knows which halo to remove whatever the mask;
- bank: the filled capture Wiener-deconvolved with the OTF at K noise-to-signal ratios (learned, log-spaced at
  start), each at unit DC gain: a classical pipeline at every regularization, from which the decoder picks locally
  (the best one is not the same near the laser, in flat regions and on edges);
- deconvolved features: F learned feature maps of (filled, saturated, halo), each Wiener-deconvolved with the OTF at a
  learned noise power (DWDN's feature-space deconvolution; codesign/models/wiener.py LearnableWiener);
- base: a learned convex mix of the bank (softmax weights), what the decoder's output corrects; a fresh network is
  that classical pipeline.

Fully convolutional: any height and width (square or not; the OTF is given on the same grid). The decoder
(codesign/models/naf.py) is local, so a large capture is decoded in overlapping tiles after one global deconvolution
(``restore_tiled``). ``model.channels`` colour channels share the feature extractor and the deconvolution (each with
its own OTF when one is given per channel) and meet in the decoder. Trained with the Charbonnier L1 loss (and
optionally the FFT loss) over the sensor's field, held to the scene at the sensor's exposure, alpha_b * b, as the main
job's SGAN is (model.target_level=exposure): no critics, no second stage.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Mapping

import torch
import torch.nn as nn
import torch.nn.functional as F

from codesign.camera import field_of_view
from codesign.config.store import register, spec_node
from codesign.errors import ConfigError, require_choice, require_list, require_number
from codesign.models import losses
from codesign.models.fill import SATURATED, field_size, push_pull_fill, valid_pixels
from codesign.models.naf import NAFUNet
from codesign.models.restorer import Restorer, TrainContext
from codesign.models.sandwich import halo_map
from codesign.models.spec import network_name
from codesign.models.wiener import LearnableWiener, wiener_filter
from codesign.spec_base import SpecMixin

# width, encoder blocks per level, middle blocks, decoder blocks per level
SIZES = {"tiny": (4, (1,), 1, (1,)), "cpu": (16, (1, 1, 1), 2, (1, 1, 1)), "paper": (32, (1, 1, 2, 4), 4, (1, 1, 1, 1))}
GUIDES = 3  # filled, saturated, halo: the per-channel maps beside the deconvolutions


@dataclass(frozen=True)
class WienerNAFSpec(SpecMixin):
    """name: the network's name (model=NAME; null: wiener_naf). size: tiny | cpu | paper (decoder width and
    blocks). channels: colour channels of the capture (1: grayscale). fe_features / fe_kernel: the learned features
    that are deconvolved; bank_nsr: the initial noise-to-signal ratios of the deconvolution bank (learned);
    gamma_init: initial noise power of the feature deconvolution; l1, fft: weights of the Charbonnier L1 and the FFT
    loss over the sensor's field; charbonnier_eps."""

    kind: str = "wiener_naf"
    name: str | None = None
    size: str = "cpu"
    channels: int = 1
    fe_features: int = 8
    fe_kernel: int = 5
    bank_nsr: tuple = (1e-4, 1e-3, 1e-2, 1e-1)
    gamma_init: float = 1e-2
    l1: float = 1.0
    fft: float = 0.0
    charbonnier_eps: float = 1e-6
    prefix: str = field(default="model", compare=False, repr=False)

    def __post_init__(self) -> None:
        p = self.prefix
        object.__setattr__(self, "name", network_name(f"{p}.name", self.name, "wiener_naf"))
        require_choice(f"{p}.size", self.size, tuple(SIZES))
        require_number(f"{p}.channels", self.channels, lo=1, hi=16, integer=True)
        require_number(f"{p}.fe_features", self.fe_features, lo=1, hi=256, integer=True)
        require_number(f"{p}.fe_kernel", self.fe_kernel, lo=1, hi=15, integer=True)
        if self.fe_kernel % 2 == 0:
            raise ConfigError(f"{p}.fe_kernel", self.fe_kernel, "must be odd (same-size convolution)")
        allowed = "must be a non-empty list of noise-to-signal ratios in [1e-8, 1e3]"
        bank = require_list(f"{p}.bank_nsr", self.bank_nsr, allowed)
        if not bank:
            raise ConfigError(f"{p}.bank_nsr", self.bank_nsr, allowed)
        object.__setattr__(self, "bank_nsr", tuple(
            float(require_number(f"{p}.bank_nsr[{i}]", v, lo=1e-8, hi=1e3)) for i, v in enumerate(bank)))
        require_number(f"{p}.gamma_init", self.gamma_init, lo=1e-7, hi=1e6)
        for key in ("l1", "fft"):
            require_number(f"{p}.{key}", getattr(self, key), lo=0)
        require_number(f"{p}.charbonnier_eps", self.charbonnier_eps, lo=0, lo_open=True, hi=1)


class Conditioner(nn.Module):
    """(capture, OTF) -> the decoder's input and the base it corrects: the global part of the network (FFTs).

    Works on every colour channel alike (they are folded into the batch): (B, C, H, W) -> (B, C * (GUIDES + K + F),
    H, W) and (B, C, H, W).
    """

    no_compile = True  # complex FFTs: torch.compile gains nothing on them (as DeconvModule)

    def __init__(self, spec: WienerNAFSpec):
        super().__init__()
        n, k = spec.fe_features, spec.fe_kernel
        # plain convolutions, no instance norm: its statistics over the whole canvas would make a pixel's features
        # depend on the size of the image around it
        self.fe = nn.Sequential(nn.Conv2d(GUIDES, n, k, padding=k // 2), nn.GELU(),
                                nn.Conv2d(n, n, 3, padding=1), nn.GELU(), nn.Conv2d(n, n, 3, padding=1))
        self.deconv = LearnableWiener(n, spec.gamma_init)
        self.log_nsr = nn.Parameter(torch.tensor([math.log(v) for v in spec.bank_nsr]))
        # the base starts as the bank's middle member (nearly: softmax of a 4-nat lead)
        logits = torch.zeros(len(spec.bank_nsr))
        logits[len(spec.bank_nsr) // 2] = 4.0
        self.mix = nn.Parameter(logits)

    def bank(self, filled: torch.Tensor, otf: torch.Tensor) -> torch.Tensor:
        """(N, 1, H, W) -> (N, K, H, W): Wiener deconvolutions at the bank's ratios, each scaled to unit DC gain."""
        nsr = self.log_nsr.exp()
        dc = otf[..., :1, :1].real.to(filled.dtype)  # H(0), broadcast per image when the OTF is per image
        gain = (dc * dc + nsr.view(-1, 1, 1)) / dc  # (K, 1, 1) or (N, K, 1, 1)
        return wiener_filter(filled.expand(-1, nsr.numel(), -1, -1), otf, 1.0, nsr.view(1, -1, 1, 1)) * gain

    def forward(self, sensor: torch.Tensor, otf: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(guide (B, C * (GUIDES + K + F), H, W): filled, saturated, halo, bank, deconvolved features per channel;
        base (B, C, H, W): the softmax mix of the bank) for ``sensor`` (B, C, H, W) and its ``otf``."""
        b, c, h, w = sensor.shape
        x = sensor.reshape(b * c, 1, h, w)
        otf = _fold_otf(otf, b, c)
        filled = push_pull_fill(x, valid_pixels(x))
        saturated = (x.detach() >= SATURATED).to(x.dtype)
        halo = halo_map(x, otf)
        bank = self.bank(filled, otf)
        feats = self.deconv(self.fe(torch.cat([filled, saturated, halo], 1)), otf)
        base = (bank * torch.softmax(self.mix, 0).view(1, -1, 1, 1)).sum(1, keepdim=True)
        guide = torch.cat([filled, saturated, halo, bank, feats.to(bank.dtype)], 1)
        return guide.reshape(b, -1, h, w), base.reshape(b, c, h, w)


def _fold_otf(otf: torch.Tensor, b: int, c: int) -> torch.Tensor:
    """The OTF for (B * C) folded images: (H, W') shared, or (C, H, W') per channel -> (B * C, 1, H, W')."""
    if otf.dim() == 2 or (otf.dim() == 3 and otf.shape[0] == 1):
        return otf.reshape(otf.shape[-2:])
    return otf.reshape(1, c, *otf.shape[-2:]).expand(b, -1, -1, -1).reshape(b * c, 1, *otf.shape[-2:])


class WienerNAF(Restorer):
    """See the module docstring."""

    kind = "wiener_naf"
    method = "wiener_naf"
    any_size = True
    mask_conditioned = True

    def __init__(self, spec: WienerNAFSpec | None = None):
        super().__init__()
        self.spec = spec if spec is not None else WienerNAFSpec()
        s = self.spec
        width, enc, mid, dec = SIZES[s.size]
        self.front = Conditioner(s)
        per_channel = GUIDES + len(s.bank_nsr) + s.fe_features
        self.decoder = NAFUNet(s.channels * per_channel, s.channels, width, enc, mid, dec)

    @classmethod
    def from_config(cls, cfg: Mapping) -> "WienerNAF":
        """From a ``model`` block: every key a WienerNAFSpec field (no separate loss block)."""
        return cls(WienerNAFSpec.from_config(dict(cfg)))

    def generators(self) -> list[nn.Module]:
        """[Conditioner (global: fill, bank, feature deconvolution), NAFUNet decoder (local)]; no critics."""
        return [self.front, self.decoder]

    # ---- restoring ----------------------------------------------------------------------------------------------
    def check_inputs(self, sensor: torch.Tensor, otf: torch.Tensor) -> None:
        """ValueError unless sensor is (B, channels, H, W) and the OTF (H, W // 2 + 1), (channels, H, W // 2 + 1)
        or (1, ...) on the same grid."""
        c = self.spec.channels
        if sensor.dim() != 4 or sensor.shape[1] != c:
            raise ValueError(f"sensor must be (B, {c}, H, W) (model.channels = {c}), got {tuple(sensor.shape)}")
        h, w = sensor.shape[-2:]
        if tuple(otf.shape[-2:]) != (h, w // 2 + 1) or otf.dim() > 3 or (otf.dim() == 3 and otf.shape[0] not in (1, c)):
            raise ValueError(f"the OTF must be ({h}, {w // 2 + 1}) or ({c}, {h}, {w // 2 + 1}) for a {h} x {w} "
                             f"sensor image (rfft2 of the PSF kernel on the same grid), got {tuple(otf.shape)}")

    def forward_with(self, generators, sensor: torch.Tensor, otf: torch.Tensor) -> dict:
        """sensor (B, C, H, W) normalized to the full well, zero outside the field; otf on the same grid. Returns
        restored (B, C, H, W) at the sensor's exposure and the base it corrected."""
        self.check_inputs(sensor, otf)
        front, decoder = generators
        guide, base = front(sensor, otf)
        return {"restored": base + decoder(guide), "base": base}

    @torch.no_grad()
    def restore_tiled(self, sensor: torch.Tensor, otf: torch.Tensor, tile: int = 512,
                      generators: list[nn.Module] | None = None,
                      progress: Callable[[int, int], None] | None = None) -> torch.Tensor:
        """The restoration of a large capture with bounded memory: the global part (fill, deconvolutions) once on
        the whole grid, then the local decoder on ``tile`` x ``tile`` tiles, each read with the decoder's reach
        of margin around it, every edge on the decoder's downsampling grid: the result equals the untiled one up to
        float round-off. ``progress(done, total)`` is called after every tile."""
        self.check_inputs(sensor, otf)
        front, decoder = self.generators() if generators is None else generators
        modes = [g.training for g in (front, decoder)]
        front.eval(), decoder.eval()
        try:
            guide, out = front(sensor, otf)
            h, w = sensor.shape[-2:]
            m = decoder.multiple
            guide = F.pad(guide, (0, -w % m, 0, -h % m), mode="replicate")  # as NAFUNet pads the whole image
            hp, wp = guide.shape[-2:]
            tile, margin = -(-tile // m) * m, -(-decoder.reach // m) * m
            boxes = [(y, x) for y in range(0, h, tile) for x in range(0, w, tile)]
            for i, (y, x) in enumerate(boxes):
                y0, x0 = max(0, y - margin), max(0, x - margin)
                part = decoder(guide[..., y0:min(hp, y + tile + margin), x0:min(wp, x + tile + margin)])
                ty, tx = min(tile, h - y), min(tile, w - x)
                out[..., y:y + ty, x:x + tx] += part[..., y - y0:y - y0 + ty, x - x0:x - x0 + tx]
                if progress is not None:
                    progress(i + 1, len(boxes))
            return out
        finally:
            for g, mode in zip((front, decoder), modes):
                g.train(mode)

    # ---- training -----------------------------------------------------------------------------------------------
    def generator_losses(self, batch: dict, out: dict, ctx: TrainContext) -> dict:
        """Charbonnier L1 (and the FFT loss when weighted) between the restoration and alpha_b * b over the
        sensor's field."""
        s = self.spec
        sensor = batch["sensor"]
        n = field_size(sensor)
        x, t = _field(out["restored"], n), _field(_exposure_target(batch), n)
        terms = {"rec2": losses.charbonnier(x, t, s.charbonnier_eps)}
        total = s.l1 * terms["rec2"]
        if s.fft > 0:
            terms["fft"] = losses.fft_loss(x, t)
            total = total + s.fft * terms["fft"]
        terms["generator_total"] = total
        return terms

    # ---- reporting ----------------------------------------------------------------------------------------------
    def summary(self) -> dict:
        """The network's name (model.name, default wiener_naf), variant "wiener_naf" and its size (tiny/cpu/paper)."""
        return {"network": self.spec.name, "variant": self.kind, "size": self.spec.size}

    def scalars(self) -> dict[str, float]:
        """The bank's learned nsr and mixing weight per member (``bank/nsr_i``, ``bank/weight_i``) and the range of the
        feature deconvolution's noise powers (``wiener/gamma_min``, ``wiener/gamma_max``)."""
        nsr = self.front.log_nsr.detach().exp()
        mix = torch.softmax(self.front.mix.detach(), 0)
        out = {f"bank/nsr_{i}": float(v) for i, v in enumerate(nsr)}
        out.update({f"bank/weight_{i}": float(v) for i, v in enumerate(mix)})
        gamma = self.front.deconv.gamma.detach()
        out.update({"wiener/gamma_min": float(gamma.min()), "wiener/gamma_max": float(gamma.max())})
        return out

    def check_input_size(self, padded_size: int, key: str = "data.padded_size") -> None:
        """ConfigError naming ``key`` below 8 pixels; any larger size works (the decoder pads to its own multiple)."""
        if padded_size < 8:
            raise ConfigError(key, padded_size, "too small for model=wiener_naf: at least 8 pixels")


def _exposure_target(batch: dict) -> torch.Tensor:
    """alpha_b * b: the scene at the exposure the sensor saw (what a camera can restore without knowing alpha_b)."""
    if batch.get("alpha_b") is None:
        raise ValueError("model=wiener_naf is held to the scene at the sensor's exposure and needs the batch's alpha_b "
                         "(B,), which SimulatedData.simulate provides; this batch has none")
    scene = batch["scene"]
    return scene * batch["alpha_b"].to(scene)[:, None, None, None]


def _field(x: torch.Tensor, n: int) -> torch.Tensor:
    """The sensor's field of a square padded training map (the simulator's centred n x n); the whole map when no
    field is found (n = 0)."""
    return x if n == 0 else field_of_view(x, n)


register("model", "wiener_naf", spec_node(WienerNAFSpec, name="wiener_naf"))
