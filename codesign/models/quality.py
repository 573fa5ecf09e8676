"""Image-quality metrics for evaluation (paper Sec. 6.3: 1-MSE, PSNR, SSIM, MS-SSIM, 1-LPIPS, DISTS).

All take (B,C,H,W) tensors in [0,1] (C = 1 in this project) and return one value per image, shape (B,), so that
callers can average over a test set. The learned metrics (LPIPS, DISTS) load their weights only from a user path.
"""
from __future__ import annotations

import re

import torch
import torch.nn as nn
import torch.nn.functional as F
from kornia.filters import get_gaussian_kernel1d
from kornia.metrics import ssim as _kornia_ssim

from codesign.errors import ConfigError
from codesign.models.vgg import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    extract,
    read_state_dict,
    require_tensor,
    vgg_from_state_dict,
)

WINDOW, SIGMA = 11, 1.5
MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)  # Wang, Simoncelli, Bovik 2003


def _check(x: torch.Tensor, y: torch.Tensor, min_size: int = 1) -> None:
    if x.ndim != 4 or x.shape != y.shape:
        raise ValueError(f"expected two (B,C,H,W) tensors of one shape, got {tuple(x.shape)} and {tuple(y.shape)}")
    if min(x.shape[-2:]) < min_size:
        raise ConfigError("image size", tuple(x.shape[-2:]), f"must be at least {min_size} x {min_size} pixels")


def mse(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(B,) mean squared error of each image pair over C, H, W."""
    _check(x, y)
    return (x - y).square().mean((1, 2, 3))


def one_minus_mse(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(B,) 1 - MSE, the paper's 1-MSE (1 for identical images, higher is better)."""
    return 1 - mse(x, y)


def psnr(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """10 log10(1 / MSE) for data range 1; +inf for identical images."""
    return -10 * torch.log10(mse(x, y))


def ssim(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Mean SSIM (Wang 2004): Gaussian window 11, sigma 1.5, K = (0.01, 0.03), data range 1, 'valid' window
    positions only (as scikit-image with gaussian_weights=True, pytorch-msssim, torchmetrics). Images >= 11 px."""
    _check(x, y, WINDOW)
    return _kornia_ssim(x, y, WINDOW, max_val=1.0, eps=0.0, padding="valid").mean((1, 2, 3))


def _ssim_terms(x: torch.Tensor, y: torch.Tensor, kernel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-image mean of the SSIM map and of the contrast-structure map cs, 'valid' window positions."""
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    t = torch.cat([x, y, x * x, y * y, x * y], 1)  # the five local moments in one separable convolution
    n = t.shape[1]
    t = F.conv2d(t, kernel.view(1, 1, -1, 1).expand(n, 1, -1, 1), groups=n)
    mx, my, exx, eyy, exy = F.conv2d(t, kernel.view(1, 1, 1, -1).expand(n, 1, 1, -1), groups=n).chunk(5, 1)
    vx, vy, cxy = exx - mx * mx, eyy - my * my, exy - mx * my
    cs = (2 * cxy + c2) / (vx + vy + c2)
    lum = (2 * mx * my + c1) / (mx * mx + my * my + c1)
    return (lum * cs).mean((1, 2, 3)), cs.mean((1, 2, 3))


def ms_ssim(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """MS-SSIM (Wang 2003): prod_j cs_j^w_j over scales j < M times SSIM_M^w_M at the coarsest, with the standard
    weights (0.0448, 0.2856, 0.3001, 0.2363, 0.1333), an 11-px Gaussian window (sigma 1.5), 'valid' positions, and
    2 x 2 average pooling between scales (odd sizes drop the last row/column, as torchmetrics). Negative cs and
    SSIM values are clamped to 0 (the usual "relu" normalization), so the result is in [0, 1].

    Five scales need min(H, W) >= 176 (176 / 2^4 = 11). Smaller images use as many scales M as fit (the scale j
    image, floor(size / 2^j), must be >= 11 px) with the first M weights renormalized to sum 1; an image of 11..21 px
    thus gets plain SSIM (clamped at 0). Images must be >= 11 px. An evaluation metric: the clamp and the
    fractional powers make its gradient undefined where a term is 0, so it is not meant as a training loss.
    """
    _check(x, y, WINDOW)
    m = 1
    while m < len(MS_SSIM_WEIGHTS) and min(x.shape[-2:]) // 2 ** m >= WINDOW:
        m += 1
    w = torch.tensor(MS_SSIM_WEIGHTS[:m], dtype=x.dtype, device=x.device)
    if m < len(MS_SSIM_WEIGHTS):
        w = w / w.sum()
    kernel = get_gaussian_kernel1d(WINDOW, SIGMA, device=x.device, dtype=x.dtype).reshape(-1)
    result = torch.ones(x.shape[0], dtype=x.dtype, device=x.device)
    for j in range(m):
        s, cs = _ssim_terms(x, y, kernel)
        term = s if j == m - 1 else cs
        result = result * term.clamp_min(0) ** w[j]
        if j < m - 1:
            x, y = F.avg_pool2d(torch.cat([x, y], 1), 2).chunk(2, 1)
    return result


# ---------------------------------------------------------------------------------------------- learned metrics

_VGG16_TAPS = (3, 8, 15, 22, 29)  # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 of VGG16
_TAP_CHANNELS = (64, 128, 256, 512, 512)


def _to_features_layout(sd: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Accept the state dicts of the official modules as well: lpips.LPIPS keeps VGG16 layer N as
    net.sliceK.N.*, DISTS_pytorch as stageK.N.*, with N the torchvision index; map both onto features.N.*."""
    out = dict(sd)
    for k, v in sd.items():
        m = re.fullmatch(r"(?:net\.slice\d|stage\d)\.(\d+)\.(weight|bias)", k)
        if m and f"features.{m[1]}.{m[2]}" not in sd:
            out[f"features.{m[1]}.{m[2]}"] = v
    return out


def _gray_to_rgb(x: torch.Tensor) -> torch.Tensor:
    return x.expand(-1, 3, -1, -1) if x.shape[1] == 1 else x


class LPIPS(nn.Module):
    """LPIPS distance (Zhang et al. 2018, VGG16 "lin" variant, v0.1); 0 for identical images, >= 0 with the
    official (non-negative) heads.

    Expected file (one ``torch.save``\\d state dict): ``features.N.weight/bias`` of torchvision's VGG16 (indices
    0..28; ``classifier.*`` ignored) and the linear heads ``lin0.model.1.weight`` .. ``lin4.model.1.weight`` of the
    official ``lpips`` package, shapes (1, C, 1, 1) with C = 64, 128, 256, 512, 512. The state dict of an
    ``lpips.LPIPS(net="vgg")`` module (VGG16 under ``net.sliceK.N.*``) is accepted as well.

    Computation: images in [0,1] -> [-1,1] -> ScalingLayer ((x - shift) / scale, shift = (-0.030, -0.088,
    -0.188), scale = (0.458, 0.448, 0.450)); taps relu1_2, relu2_2, relu3_3, relu4_3, relu5_3; each feature divided
    by its L2 norm over channels (+1e-10); squared difference weighted by the head (1x1 conv), averaged over space,
    summed over the five layers. Grayscale is replicated to 3 channels. Inputs must be >= 16 px (four poolings).
    """

    def __init__(self, path, key: str = "evaluate.lpips_weights"):
        super().__init__()
        sd = _to_features_layout(read_state_dict(path, key))
        self.features = vgg_from_state_dict("vgg16", sd, path, key)[: max(_VGG16_TAPS) + 1]
        what = "VGG16 features.* plus the LPIPS heads lin0.model.1.weight .. lin4.model.1.weight"
        heads = [require_tensor(sd, f"lin{i}.model.1.weight", (1, c, 1, 1), path, key, what).float()
                 for i, c in enumerate(_TAP_CHANNELS)]
        for i, h in enumerate(heads):
            self.register_buffer(f"lin{i}", h.clone())
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """(B,) LPIPS distance of each image pair (B,C,H,W) in [0,1], both through one VGG16 pass; >= 16 px."""
        _check(x, y, 16)
        b = x.shape[0]
        z = (_gray_to_rgb(torch.cat([x, y], 0)) * 2 - 1 - self.shift.to(x.dtype)) / self.scale.to(x.dtype)
        total = torch.zeros(b, dtype=x.dtype, device=x.device)
        for i, f in enumerate(extract(self.features, z, _VGG16_TAPS)):
            f = f / (f.square().sum(1, keepdim=True).sqrt() + 1e-10)
            d = (f[:b] - f[b:]).square()
            total = total + F.conv2d(d, getattr(self, f"lin{i}").to(x.dtype)).mean((1, 2, 3))
        return total


class _L2Pool(nn.Module):
    """DISTS's replacement of max pooling: sqrt(hann3x3 * x^2 + 1e-12) per channel, stride 2, padding 1; the 3 x 3
    window is the outer product of [0.5, 1, 0.5] normalized to sum 1."""

    def __init__(self):
        super().__init__()
        a = torch.tensor([0.5, 1.0, 0.5])
        k = torch.outer(a, a)
        self.register_buffer("kernel", (k / k.sum()).view(1, 1, 3, 3), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        c = x.shape[1]
        k = self.kernel.to(x.dtype).expand(c, 1, 3, 3)
        return (F.conv2d(x.square(), k, stride=2, padding=1, groups=c) + 1e-12).sqrt()


class DISTS(nn.Module):
    """DISTS distance (Ding et al. 2020); 0 for identical images (exactly, see ``forward``), 1 - similarity.

    Expected file (one ``torch.save``\\d state dict): ``features.N.weight/bias`` of torchvision's VGG16 (indices
    0..28) plus the official ``alpha`` and ``beta`` tensors, each of shape (1, 1475, 1, 1) (1475 = 3 + 64 + 128 +
    256 + 512 + 512 channels: the input image and five VGG stages). The state dict of a ``DISTS_pytorch.DISTS``
    module (VGG16 under ``stageK.N.*``) is accepted as well.

    Computation as in the official implementation: the four max poolings of VGG16 become L2 poolings; features are
    the ImageNet-normalized network's relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 plus the raw [0,1] image; per
    channel, S1 = (2 mu_x mu_y + c) / (mu_x^2 + mu_y^2 + c) and S2 = (2 cov + c) / (var_x + var_y + c) over space,
    c = 1e-6; alpha and beta are normalized by their total sum w; D = 1 - sum(alpha S1 + beta S2) / w. Grayscale
    is replicated to 3 channels. The official package's optional resize of large inputs is not applied.
    """

    def __init__(self, path, key: str = "evaluate.dists_weights"):
        super().__init__()
        sd = _to_features_layout(read_state_dict(path, key))
        features = vgg_from_state_dict("vgg16", sd, path, key)[: max(_VGG16_TAPS) + 1]
        self.features = nn.Sequential(*[_L2Pool() if isinstance(m, nn.MaxPool2d) else m for m in features])
        what = "VGG16 features.* plus DISTS alpha and beta of shape (1, 1475, 1, 1)"
        n = 3 + sum(_TAP_CHANNELS)
        self.register_buffer("alpha", require_tensor(sd, "alpha", (1, n, 1, 1), path, key, what).float().clone())
        self.register_buffer("beta", require_tensor(sd, "beta", (1, n, 1, 1), path, key, what).float().clone())
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Evaluated as sum(alpha (1 - S1) + beta (1 - S2)) / w, equal to 1 - sum(alpha S1 + beta S2) / w because
        the normalized weights sum to 1, but exactly 0 when S1 = S2 = 1 (identical images); the covariance is
        mean((x - mu_x)(y - mu_y)), algebraically the official E[xy] - mu_x mu_y, so that S2 is exactly 1 then."""
        _check(x, y)
        b = x.shape[0]
        z = _gray_to_rgb(torch.cat([x, y], 0))
        feats = [z] + extract(self.features, (z - self.mean.to(x.dtype)) / self.std.to(x.dtype), _VGG16_TAPS)
        alpha, beta = self.alpha.to(x.dtype).flatten(), self.beta.to(x.dtype).flatten()
        wsum = alpha.sum() + beta.sum()
        total = torch.zeros(b, dtype=x.dtype, device=x.device)
        start, c = 0, 1e-6
        for f in feats:
            fx, fy = f[:b], f[b:]
            n = f.shape[1]
            mx, my = fx.mean((2, 3)), fy.mean((2, 3))
            dx, dy = fx - mx[..., None, None], fy - my[..., None, None]
            vx, vy, cov = dx.square().mean((2, 3)), dy.square().mean((2, 3)), (dx * dy).mean((2, 3))
            s1 = (2 * mx * my + c) / (mx * mx + my * my + c)
            s2 = (2 * cov + c) / (vx + vy + c)
            total = total + ((1 - s1) * alpha[start:start + n] + (1 - s2) * beta[start:start + n]).sum(1)
            start += n
        return total / wsum


def load_lpips(path, key: str = "evaluate.lpips_weights") -> LPIPS:
    """LPIPS distance callable (x, y) -> (B,) from ``path`` (layout in :class:`LPIPS`); ConfigError on a bad file."""
    return LPIPS(path, key)


def load_dists(path, key: str = "evaluate.dists_weights") -> DISTS:
    """DISTS distance callable (x, y) -> (B,) from ``path`` (layout in :class:`DISTS`); ConfigError on a bad file."""
    return DISTS(path, key)


class OneMinus(nn.Module):
    """1 - metric(x, y) without gradients, in float32 on the inputs' device (the network follows the inputs there on
    first use, so an evaluator need not move it), returned in the inputs' dtype."""

    def __init__(self, metric: nn.Module):
        super().__init__()
        self.metric = metric

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """(B,) similarity 1 - metric(x, y) in ``x``'s dtype, the metric moved to ``x``'s device on first use."""
        if next(self.metric.buffers()).device != x.device:
            self.metric.to(x.device)
        with torch.no_grad():
            return (1 - self.metric(x.float(), y.float())).to(x.dtype)


def perceptual_metrics(lpips_path, dists_path) -> dict[str, OneMinus | str]:
    """{"one_minus_lpips": ..., "one_minus_dists": ...}: each a callable module (x, y) -> (B,) similarity (1 for
    identical images, higher is better, as the paper's table reports 1-LPIPS and DISTS), or a string saying why it
    is unavailable. A path that is given but wrong raises ConfigError rather than silently dropping the metric."""
    out: dict[str, OneMinus | str] = {}
    for name, path, key, loader in (("one_minus_lpips", lpips_path, "evaluate.lpips_weights", load_lpips),
                                    ("one_minus_dists", dists_path, "evaluate.dists_weights", load_dists)):
        if path is None or str(path) == "":
            out[name] = f"unavailable: no weights path ({key})"
        else:
            out[name] = OneMinus(loader(path, key))
    return out
