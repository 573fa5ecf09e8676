"""Classical hole filling for the sensor image: saturated pixels (the laser footprint) and the zero padding around
the sensor's field are replaced by a smooth continuation of the valid pixels around them (push-pull pyramid).

Why in the network: G1 is the stage that inpaints the laser and outpaints the border (supplement Sec. 2). Starting
its residual from the sensor image itself makes its first training steps spend themselves on those two jobs, with
corrections as large as the image's own contrast, and the restoration of an unlasered image gets worse before it
gets better (docs/models.md). Starting from the filled image, G1 corrects a reasonable estimate instead.

Push: each level halves the resolution, averaging only valid pixels (a pixel of the coarser level is valid when any
of its four children is). Pull: from the coarsest level up, every invalid pixel takes the bilinearly upsampled value
of the level below. Valid pixels are returned unchanged; the result is differentiable in the image.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

SATURATED = 0.999  # the normalized sensor image reads exactly 1 at full well; partially saturated network pixels
# (a k x k average of sensor pixels) just below it are kept as measured


def valid_pixels(sensor: torch.Tensor, saturated: float = SATURATED) -> torch.Tensor:
    """Pixels the sensor measured: inside the field (the padding is exactly 0) and below saturation."""
    return (sensor > 0) & (sensor < saturated)


def saturated_fraction(sensor: torch.Tensor, saturated: float = SATURATED) -> torch.Tensor:
    """(B,) share of each image's field (the non-zero pixels, as in valid_pixels) at saturation."""
    field = (sensor > 0).flatten(1).sum(1).clamp_min(1)
    return (sensor >= saturated).flatten(1).sum(1).to(sensor.dtype) / field


def push_pull_fill(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """``x`` (B, C, H, W) with every pixel where ``valid`` is False replaced by a smooth continuation of the valid
    ones (an image without any valid pixel is returned as it is)."""
    levels = [(x, valid.to(x.dtype))]
    # down to one pixel along both sides: a non-square image reaches one along its short side first, where holes
    # along the long side may remain (that side alone keeps halving)
    while max(levels[-1][0].shape[-2:]) > 1 and bool((levels[-1][1] == 0).any()):
        xv, v = levels[-1]
        k = tuple(2 if n > 1 else 1 for n in xv.shape[-2:])
        num = F.avg_pool2d(xv * v, k, ceil_mode=True)
        den = F.avg_pool2d(v, k, ceil_mode=True)
        levels.append((num / den.clamp_min(1e-12), (den > 0).to(x.dtype)))
    filled = levels[-1][0]
    for xv, v in reversed(levels[:-1]):
        up = F.interpolate(filled, size=xv.shape[-2:], mode="bilinear", align_corners=False)
        filled = v * xv + (1 - v) * up
    return torch.where(valid.flatten(-2).any(-1)[..., None, None], filled, x)


def replicate_pad(x: torch.Tensor, n: int) -> torch.Tensor:
    """Central n x n of a padded (..., P, P) image (the sensor's field, (P - n) // 2 before it), padded back to P by
    edge replication: the classical Wiener's padding (it rings less than zeros) and model.g2_base_pad=replicate's."""
    p = x.shape[-1]
    m = (p - n) // 2
    return F.pad(x[..., m:m + n, m:m + n], (m, p - n - m, m, p - n - m), mode="replicate")


def replicate_outside_field(x: torch.Tensor, sensor: torch.Tensor) -> torch.Tensor:
    """``x`` (B, C, P, P) with everything outside the sensor's field (the centred square of non-zero pixels of
    ``sensor``, the simulator's crop of the padded canvas) replaced by edge replication of the field's border
    (replicate_pad, as the evaluation's classical Wiener pads); ``x`` unchanged when the field fills the canvas or is
    empty. Differentiable in ``x``."""
    n = field_size(sensor)
    return x if n in (0, x.shape[-1]) else replicate_pad(x, n)


def field_size(sensor: torch.Tensor) -> int:
    """The side of the sensor's field in a padded (B, C, P, P) sensor image: the most rows of any image holding a
    non-zero pixel (the padding is exactly 0; a dark pixel inside the field may be 0 too, a whole dark row of every
    image is not expected); 0 for an empty batch. One host sync."""
    return int((sensor > 0).any(-1).flatten(1).sum(1).max()) if sensor.numel() else 0
