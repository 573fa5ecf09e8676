"""The sandwich's data path, b^ = G2(G_v(G1(s, x, y), h)), with the generators given (the model's own or EMA copies):
G1's inputs (coordinate channels, the halo channel), its residual and laser-gated correction, G2's presence and
level gain, and the two-scale pyramid G2 outputs and is compared with. The model, its objective and its critics:
codesign/models/sgan.py."""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from codesign.models.fill import SATURATED, push_pull_fill, replicate_outside_field, valid_pixels
from codesign.models.spec import ModelSpec


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


HALO_DECADES = 6.0  # the halo channel's range: 1 at the laser's centre down to 0 at 1e-6 of it


def halo_map(sensor: torch.Tensor, otf: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) where the laser's light lies, from the system PSF (``otf`` on the same grid, its kernel at the
    origin) spread over the saturated pixels: log10 of (PSF * saturated) relative to its maximum, mapped from
    [-HALO_DECADES, 0] to [0, 1]; 0 everywhere in an image without saturated pixels (model.g1_halo). The shape of the halo around the
    footprint is the mask's: this is what tells one G1 which halo to remove whatever mask it is given."""
    # in float64: float32 FFT round-off (~1e-7 of the peak) would sit near the channel's floor
    sat = (sensor.detach() >= SATURATED).double()
    spread = torch.fft.irfft2(torch.fft.rfft2(sat) * otf.to(torch.complex128), s=sensor.shape[-2:]).clamp_min(0)
    peak = spread.amax(dim=(-2, -1), keepdim=True)
    rel = spread / peak.clamp_min(torch.finfo(spread.dtype).tiny)
    level = (1 + torch.log10(rel.clamp_min(10 ** -HALO_DECADES)) / HALO_DECADES).clamp(0, 1)
    return torch.where(peak > 0, level, torch.zeros_like(level)).to(sensor.dtype)


def pre_restore(g1: nn.Module, sensor: torch.Tensor, residual: bool, base: str = "sensor",
                gate: torch.Tensor | None = None, halo: torch.Tensor | None = None) -> torch.Tensor:
    """I_b^ = G1(s, x, y[, halo]), or with ``residual`` a correction added to the sensor image (``base`` "sensor")
    or to the sensor image with its saturated and padded pixels filled from their surroundings ("filled"); ``gate``
    (B,): scales the correction per image (model.laser_gate); ``halo``: halo_map's channel (model.g1_halo)."""
    inputs = torch.cat([sensor, coordinates(sensor)] + ([halo] if halo is not None else []), 1)
    if not residual:
        return g1(inputs)
    out = g1(inputs) if gate is None else gated_correction(g1, inputs, gate)
    return (sensor if base == "sensor" else push_pull_fill(sensor, valid_pixels(sensor))) + out


def gated_correction(g1: nn.Module, inputs: torch.Tensor, gate: torch.Tensor) -> torch.Tensor:
    """g1(inputs) * gate per image, G1 run only on the images whose gate is open. A closed gate (no saturated pixel:
    p = 0 exactly, and so is its derivative) makes the image's correction and every gradient through it exactly 0,
    and G1 holds only per-image layers (instance norms), so the open images' outputs do not depend on the others:
    the result is the whole batch's. An image without a laser then costs no G1 work, in training and in use.
    On the CPU only, with G1 a plain module: on a GPU the data-dependent batch would synchronize the stream and
    break graph capture, under DistributedDataParallel a rank whose images all skip would leave G1 without a
    gradient, and a compiled G1 would be recompiled for every batch size."""
    g = gate[:, None, None, None]
    if inputs.device.type != "cpu" or plain_module(g1) is not g1 or hasattr(g1, "_orig_mod"):
        return g1(inputs) * g
    live = (gate > 0).nonzero().squeeze(1)
    if len(live) == len(gate):
        return g1(inputs) * g
    out = inputs.new_zeros((inputs.shape[0], 1, *inputs.shape[2:]))
    if len(live) == 0:
        return out
    return out.index_copy(0, live, g1(inputs[live]) * g[live])


def laser_presence(g2: nn.Module, sensor: torch.Tensor, spec: ModelSpec) -> torch.Tensor | None:
    """(B,) presence of a laser in each image (model.laser_gate; G2 holds its parameter), None when off."""
    return plain_module(g2).laser_presence(sensor) if spec.laser_gate else None


def level_presence(presence: torch.Tensor | None, spec: ModelSpec) -> torch.Tensor | None:
    """The presence that scales the level head's log gain by 1 - p (in use and in its fit), or None: held to the
    scene, a lasered output is G2's, which training brought to the scene's level; held to the exposure
    (model.target_level), every output sits at the sensor's level and gets the whole gain."""
    return presence if spec.target_level == "scene" else None


def plain_module(m: nn.Module) -> nn.Module:
    """The module under a DistributedDataParallel wrapper (which forwards only ``forward``): G2's presence and base
    use its scalars outside its forward; their gradients still reach DDP's per-parameter hooks and are averaged."""
    return getattr(m, "module", m)


def sandwich(generators, sensor: torch.Tensor, otf: torch.Tensor, spec: ModelSpec) -> dict:
    """G2(G_v(G1(s, x, y), h)) with the given (g1, gv, g2) modules (the model's own, or e.g. EMA copies); the
    residual paths as ``spec`` says (g1_residual, g1_base, g2_residual: G2's outputs correct I_b^; laser_gate,
    g2_gate)."""
    p = sensor.shape[-1]
    if sensor.shape[-2] != p or tuple(otf.shape[-2:]) != (p, p // 2 + 1):
        raise ValueError(f"sensor must be (B, 1, P, P) with an OTF of shape (P, P // 2 + 1); got sensor "
                         f"{tuple(sensor.shape)} and OTF {tuple(otf.shape)}")
    g1, gv, g2 = generators
    presence = laser_presence(g2, sensor, spec)
    halo = halo_map(sensor, otf) if spec.g1_halo else None
    i_b = pre_restore(g1, sensor, spec.g1_residual, spec.g1_base, presence, halo)
    features = gv(i_b, otf)
    base = None
    if spec.g2_residual:  # model.g2_base_pad: what lies outside the field when the base deconvolves I_b^
        padded = replicate_outside_field(i_b, sensor) if spec.g2_base_pad == "replicate" else i_b
        base = plain_module(g2).base(padded, otf, presence)
    b = g2(features, base, presence if spec.g2_gate else None)
    exposure = b  # G2's own output, at the sensor's exposure when held to it (model.target_level)
    if spec.level_head:  # both scales brought to the scene's level by one gain per image (no gradient through it)
        gain = plain_module(g2).level.gain(b[1], sensor, level_presence(presence, spec))[:, None, None, None]
        b = [gain * x for x in b]
    out = {"i_b": i_b, "features": features, "b": b, "restored": b[1]}
    if spec.target_level == "exposure":
        out["b_exposure"] = exposure
    if base is not None:  # what G2's learned correction is added to (the network without that correction)
        out["base"] = base
    return out
