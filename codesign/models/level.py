"""model.level_head: the restored image brought to the scene's level, a gain per image estimated from its histogram.

The sensor sees alpha_b * b (the background strength alpha_b ~ U[0.3, 0.7] of Sec. 6.2, independent of the scene,
scales the whole image), while the network is scored against b. A restorer that only deblurs and inpaints leaves its
output at the sensor's level, and a fixed gain cannot fit every alpha_b: the best constant gives a plain PSNR near
16 dB however good the restoration (docs/models.md Sec. 12). What the image does say about alpha_b is in its
histogram (natural scenes fill their 8-bit range in a typical way), so the head maps the log quantiles of the output,
over the pixels the sensor measured below saturation, to a log gain, linear in those features and their squares.

It is fitted, not trained step by step: a least-squares fit (ridge) of each image's best log gain on training-split
crops drawn as in training, half of them without a laser, at the end of a training, on the restoring generators
(codesign/models/sgan.py SGAN.calibrate); before that fit (weight 0) the gain is exactly 1. The training
distribution's lasers (alpha_l uniform on [0, 2e6]) leave almost no unlasered image in training, so the gated
network's unlasered output is its Wiener base at the sensor's level; its lasered output is G2's, which training
already pulled towards the scene's level. Hence the log gain is scaled by 1 - p, p the laser's presence
(model.laser_gate), in the fit as in use.
"""
from __future__ import annotations

import torch
import torch.nn as nn

from codesign.models.fill import valid_pixels

QUANTILES = (0.05, 0.2, 0.35, 0.5, 0.65, 0.8, 0.9, 0.95, 0.98, 0.99, 0.995, 0.999)
N_FEATURES = 1 + 3 * len(QUANTILES)  # 1, log q, (log q)^2, log q * log q_top
GAIN_RANGE = (0.2, 5.0)  # the fitted gain is clamped here: 1 / 0.7 to 1 / 0.3 and a margin for the blur
FLOOR = 1e-4  # quantiles below this (a black crop) are read as this before the log
RIDGE = 1e-3  # ridge weight of the fit, per sample, on every feature but the constant


def field_quantiles(x: torch.Tensor, field: torch.Tensor) -> torch.Tensor:
    """(B, len(QUANTILES)) quantiles of each image of ``x`` (B, 1, P, P) over its ``field`` pixels (bool, same
    shape; at least one per image), by linear interpolation between order statistics, as torch.quantile does."""
    flat, keep = x.flatten(1), field.flatten(1)
    n = keep.sum(1).clamp_min(1)  # (no host read here: this runs in training steps)
    # pixels outside the field sort to the end; the k-th order statistic of the field is then column k
    ordered = torch.where(keep, flat, torch.full_like(flat, float("inf"))).sort(1).values
    q = torch.tensor(QUANTILES, dtype=flat.dtype, device=flat.device)
    last = (n[:, None] - 1).long()
    pos = q[None] * last.to(flat.dtype)
    lo = pos.floor().long()
    hi = torch.minimum(lo + 1, last)
    w = pos - lo.to(flat.dtype)
    return ordered.gather(1, lo) * (1 - w) + ordered.gather(1, hi) * w


def level_features(x: torch.Tensor, sensor: torch.Tensor) -> torch.Tensor:
    """(B, N_FEATURES) float64 features of the head: 1, log q, (log q)^2 and log q * log q_top, with q the
    quantiles of ``x`` over the pixels the sensor measured below saturation (the laser's footprint tells nothing of
    the scene's level)."""
    lq = field_quantiles(x.detach().double(), valid_pixels(sensor)).clamp_min(FLOOR).log()
    return torch.cat([torch.ones_like(lq[:, :1]), lq, lq * lq, lq * lq[:, -1:]], 1)


def best_log_gain(x: torch.Tensor, target: torch.Tensor, field: torch.Tensor) -> torch.Tensor:
    """(B,) log of the gain that brings each image of ``x`` closest to ``target`` in squared error over the field:
    log(<x, t> / <x, x>); NaN where that gain is not positive (a dark or inverted image: left out of a fit)."""
    x, t, f = x.double().flatten(1), target.double().flatten(1), field.flatten(1).double()
    gain = (x * t * f).sum(1) / (x * x * f).sum(1)
    return torch.where(gain > 0, gain.clamp_min(1e-300).log(), torch.full_like(gain, float("nan")))


def fit_weight(features: torch.Tensor, log_gain: torch.Tensor, ridge: float = RIDGE) -> torch.Tensor:
    """The head's weight (N_FEATURES,) float64: ridge least squares of ``log_gain`` (B,) on ``features`` (B, F), the
    constant unpenalized; rows with a NaN target are left out. ValueError with fewer usable rows than 2."""
    ok = torch.isfinite(log_gain)
    a, y = features[ok].double(), log_gain[ok].double()
    if a.shape[0] < 2:
        raise ValueError(f"the level fit needs at least 2 images with a positive best gain, got {a.shape[0]}")
    reg = torch.full((a.shape[1],), ridge * a.shape[0], dtype=a.dtype, device=a.device)
    reg[0] = 0.0
    return torch.linalg.solve(a.T @ a + torch.diag(reg), a.T @ y)


class LevelHead(nn.Module):
    """The gain g = exp(features . weight), clamped to GAIN_RANGE; weight is a buffer (set by a fit, never by the
    optimizer), 0 until fitted (gain 1). ``fitted`` is known on the host (set by ``set_weight`` and by loading), so
    a training step never reads the weight back."""

    def __init__(self):
        super().__init__()
        self.register_buffer("weight", torch.zeros(N_FEATURES, dtype=torch.float64))
        self.fitted = False

    @torch.no_grad()
    def set_weight(self, weight: torch.Tensor) -> None:
        """Install a fitted weight (N_FEATURES,) (``fit_weight``) and note on the host whether the head is fitted
        (a zero weight: gain exactly 1)."""
        self.weight.copy_(weight)
        self.fitted = bool(self.weight.any())

    def gain(self, x: torch.Tensor, sensor: torch.Tensor, presence: torch.Tensor | None = None) -> torch.Tensor:
        """(B,) gain of each image of ``x`` (B, 1, P, P), the restoration of ``sensor``, in x's dtype (no
        gradient); with the laser's ``presence`` p (B,) in [0, 1] (model.laser_gate) the log gain is scaled by
        1 - p: the head is fitted on unlasered images, and a gated network's lasered output is G2's, which its
        training brought to the scene's level already."""
        if not self.fitted:  # exactly 1, and no sort on the training path
            return torch.ones(x.shape[0], dtype=x.dtype, device=x.device)
        log_gain = level_features(x, sensor) @ self.weight.double()
        if presence is not None:
            log_gain = log_gain * (1 - presence.detach().double())
        g = log_gain.exp().clamp(*GAIN_RANGE)
        return g.to(x.dtype)

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                              error_msgs):
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                                      error_msgs)
        self.fitted = bool(self.weight.any())
