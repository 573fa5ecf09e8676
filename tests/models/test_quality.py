"""Evaluation metrics: closed forms, references (scikit-image SSIM, a float64 scipy MS-SSIM), LPIPS/DISTS from a
user file with random weights (structure only: the official weights are not available here)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.signal import convolve2d
from skimage.metrics import structural_similarity

from codesign.errors import ConfigError
from codesign.models.vgg import extract, vgg16_features
from codesign.models.quality import (DISTS, LPIPS, MS_SSIM_WEIGHTS, _L2Pool, load_dists, load_lpips, ms_ssim, mse,
                              one_minus_mse, perceptual_metrics, psnr, ssim)


def images(shape, seed=0, noise=0.0):
    """A smooth random scene in [0,1] and a noisy copy (clamped)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.nn.functional.interpolate(torch.rand(shape[0], 1, shape[2] // 4 + 1, shape[3] // 4 + 1, generator=g,
                                                   dtype=torch.float64), size=shape[2:], mode="bilinear")
    return x, (x + noise * torch.randn(x.shape, generator=g, dtype=torch.float64)).clamp(0, 1)


def test_mse_psnr():
    x = torch.zeros(3, 1, 4, 5, dtype=torch.float64)
    y = x + torch.tensor([0.1, 0.01, 0.5], dtype=torch.float64).view(3, 1, 1, 1)
    torch.testing.assert_close(mse(x, y), torch.tensor([1e-2, 1e-4, 0.25], dtype=torch.float64))
    torch.testing.assert_close(one_minus_mse(x, y), 1 - mse(x, y))
    torch.testing.assert_close(psnr(x, y), 10 * torch.log10(1 / mse(x, y)))
    torch.testing.assert_close(psnr(x, y)[:2], torch.tensor([20.0, 40.0], dtype=torch.float64))
    a, b = images((2, 1, 16, 16), noise=0.1)
    torch.testing.assert_close(psnr(a, b), 10 * torch.log10(1 / ((a - b) ** 2).mean((1, 2, 3))))
    assert psnr(a, a).isinf().all()


def test_ssim_identity_and_skimage():
    x, y = images((2, 1, 40, 48), noise=0.1)
    assert (ssim(x, x) == 1).all()
    ref = [structural_similarity(x[i, 0].numpy(), y[i, 0].numpy(), gaussian_weights=True, sigma=1.5,
                                 use_sample_covariance=False, data_range=1.0) for i in range(2)]
    torch.testing.assert_close(ssim(x, y), torch.tensor(ref, dtype=torch.float64), rtol=0, atol=1e-10)
    with pytest.raises(ConfigError, match="11 x 11"):
        ssim(x[..., :10, :], y[..., :10, :])


def ref_ms_ssim(a: np.ndarray, b: np.ndarray) -> float:
    """float64 MS-SSIM of two 2-D arrays: scipy 'valid' Gaussian convolution, 2x2 block means between scales."""
    g = np.exp(-((np.arange(11) - 5.0) ** 2) / (2 * 1.5 ** 2))
    g = g / g.sum()

    def blur(t):
        return convolve2d(convolve2d(t, g[:, None], "valid"), g[None, :], "valid")

    c1, c2 = 1e-4, 9e-4
    m = 1
    while m < 5 and min(a.shape) // 2 ** m >= 11:
        m += 1
    w = np.array(MS_SSIM_WEIGHTS[:m])
    w = w / w.sum() if m < 5 else w
    out = 1.0
    for j in range(m):
        mu_a, mu_b = blur(a), blur(b)
        va, vb, cab = blur(a * a) - mu_a ** 2, blur(b * b) - mu_b ** 2, blur(a * b) - mu_a * mu_b
        cs = (2 * cab + c2) / (va + vb + c2)
        s = (2 * mu_a * mu_b + c1) / (mu_a ** 2 + mu_b ** 2 + c1) * cs
        out *= max((s if j == m - 1 else cs).mean(), 0.0) ** w[j]
        h, v = a.shape[0] // 2, a.shape[1] // 2
        a = a[:2 * h, :2 * v].reshape(h, 2, v, 2).mean((1, 3))
        b = b[:2 * h, :2 * v].reshape(h, 2, v, 2).mean((1, 3))
    return out


@pytest.mark.parametrize("size", [(176, 181), (64, 70), (21, 30)])  # 5 scales; 3 scales; 1 scale (= SSIM)
def test_ms_ssim_reference(size):
    x, y = images((2, 1) + size, noise=0.1)
    assert (ms_ssim(x, x) == 1).all()
    ref = torch.tensor([ref_ms_ssim(x[i, 0].numpy(), y[i, 0].numpy()) for i in range(2)], dtype=torch.float64)
    torch.testing.assert_close(ms_ssim(x, y), ref, rtol=1e-10, atol=0)
    if size[0] < 22:
        torch.testing.assert_close(ms_ssim(x, y), ssim(x, y))


def test_ms_ssim_decreases_with_noise_and_clamps():
    x, _ = images((1, 1, 96, 96))
    noise = torch.randn((1, 1, 96, 96), generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    sigma = torch.tensor([0.0, 0.02, 0.05, 0.1, 0.3], dtype=torch.float64).view(-1, 1, 1, 1)
    scores = ms_ssim(x.expand(5, -1, -1, -1), (x + sigma * noise).clamp(0, 1)).tolist()
    assert scores[0] == 1 and all(a > b for a, b in zip(scores, scores[1:])) and scores[-1] > 0
    x, _ = images((1, 1, 64, 64))
    assert ms_ssim(x, 1 - x).item() == 0.0  # anti-correlated: negative cs clamped to 0
    x32 = x.float()
    assert ms_ssim(x32, x32).dtype == torch.float32


# ------------------------------------------------------------------------------------------------ LPIPS / DISTS

def learned_state_dict(seed=0):
    """Random VGG16 features (He scale) + non-negative LPIPS heads + positive DISTS alpha/beta, official names."""
    g = torch.Generator().manual_seed(seed)
    sd = {}
    with torch.device("meta"):  # shapes only
        shapes = vgg16_features().state_dict()
    for k, v in shapes.items():
        sd[f"features.{k}"] = torch.randn(v.shape, generator=g) * (2 / v[0].numel()) ** 0.5 if v.ndim > 1 else \
            torch.zeros(v.shape)
    for i, c in enumerate((64, 128, 256, 512, 512)):
        sd[f"lin{i}.model.1.weight"] = torch.rand(1, c, 1, 1, generator=g) / c
    sd["alpha"] = torch.rand(1, 1475, 1, 1, generator=g) + 0.1
    sd["beta"] = torch.rand(1, 1475, 1, 1, generator=g) + 0.1
    return sd


@pytest.fixture(scope="module")
def learned(tmp_path_factory):
    sd = learned_state_dict()
    path = tmp_path_factory.mktemp("learned") / "lpips_dists.pth"
    torch.save(sd, path)
    return path, sd


def test_lpips_structure(learned):
    path, _ = learned
    lp = load_lpips(path)
    assert isinstance(lp, LPIPS) and all(not p.requires_grad for p in lp.parameters())
    x, y = images((2, 1, 32, 32), noise=0.05)
    _, z = images((2, 1, 32, 32), noise=0.3)
    same, near, far = lp(x.float(), x.float()), lp(x.float(), y.float()), lp(x.float(), z.float())
    assert same.shape == (2,) and (same == 0).all()
    assert torch.isfinite(far).all() and (near > 0).all() and (far > near).all()
    torch.testing.assert_close(lp(x.float(), y.float()), lp(y.float(), x.float()))  # symmetric


def official_dists(m: DISTS, x, y):
    """The official formula, 1 - sum(alpha S1 + beta S2) / w with cov = E[xy] - mu_x mu_y."""
    b = x.shape[0]
    z = torch.cat([x, y]).expand(-1, 3, -1, -1)
    feats = [z] + extract(m.features, (z - m.mean) / m.std, (3, 8, 15, 22, 29))
    a, be = m.alpha.flatten(), m.beta.flatten()
    w, s, i = a.sum() + be.sum(), 0, 0
    for f in feats:
        fx, fy, n = f[:b], f[b:], f.shape[1]
        mx, my = fx.mean((2, 3)), fy.mean((2, 3))
        vx, vy = ((fx - mx[..., None, None]) ** 2).mean((2, 3)), ((fy - my[..., None, None]) ** 2).mean((2, 3))
        cov = (fx * fy).mean((2, 3)) - mx * my
        s1 = (2 * mx * my + 1e-6) / (mx ** 2 + my ** 2 + 1e-6)
        s2 = (2 * cov + 1e-6) / (vx + vy + 1e-6)
        s = s + (a[i:i + n] * s1 + be[i:i + n] * s2).sum(1) / w
        i += n
    return 1 - s


def test_dists_structure(learned):
    path, _ = learned
    d = load_dists(path)
    assert isinstance(d, DISTS) and sum(isinstance(mod, _L2Pool) for mod in d.features) == 4
    x, y = images((2, 1, 32, 32), noise=0.05)
    _, z = images((2, 1, 32, 32), noise=0.3)
    x, y, z = x.float(), y.float(), z.float()
    assert (d(x, x) == 0).all()  # exactly: evaluated as sum(alpha (1 - S1) + beta (1 - S2)) / w
    near, far = d(x, y), d(x, z)
    assert (near > 0).all() and (far > near).all() and (far < 1).all()
    torch.testing.assert_close(near, official_dists(d, x, y), rtol=1e-4, atol=1e-6)


def test_l2pool():
    p = _L2Pool()
    out = p(torch.full((1, 2, 8, 8), 0.7, dtype=torch.float64))
    assert out.shape == (1, 2, 4, 4)
    torch.testing.assert_close(out[..., 1:, 1:], torch.full((1, 2, 3, 3), 0.7, dtype=torch.float64))  # interior
    torch.testing.assert_close(out[0, 0, 0, 0], torch.tensor(0.7 * math.sqrt(9 / 16), dtype=torch.float64))


def test_official_module_layouts(learned, tmp_path):
    path, sd = learned
    x, y = images((1, 1, 32, 32), noise=0.1)
    x, y = x.float(), y.float()
    stages = [(0, 4), (4, 9), (9, 16), (16, 23), (23, 30)]

    def renamed(fmt):
        out = {k: v for k, v in sd.items() if not k.startswith("features.")}
        for k, v in sd.items():
            if k.startswith("features."):
                n = int(k.split(".")[1])
                stage = next(s for s, (lo, hi) in enumerate(stages, 1) if lo <= n < hi)
                out[fmt.format(stage=stage) + k[len("features."):]] = v
        return out

    p1, p2 = tmp_path / "lpips_module.pth", tmp_path / "dists_module.pth"
    torch.save(renamed("net.slice{stage}."), p1)
    torch.save(renamed("stage{stage}."), p2)
    torch.testing.assert_close(load_lpips(p1)(x, y), load_lpips(path)(x, y))
    torch.testing.assert_close(load_dists(p2)(x, y), load_dists(path)(x, y))


def test_learned_metric_errors(learned, tmp_path):
    _, sd = learned
    bad = dict(sd)
    del bad["lin3.model.1.weight"]
    p = tmp_path / "bad.pth"
    torch.save(bad, p)
    with pytest.raises(ConfigError) as e:
        load_lpips(p)
    assert "evaluate.lpips_weights" in str(e.value) and "'lin3.model.1.weight'" in str(e.value)
    assert "(1, 512, 1, 1)" in str(e.value) and str(p) in str(e.value)
    bad["alpha"] = torch.ones(1, 1472, 1, 1)
    torch.save(bad, p)
    with pytest.raises(ConfigError, match=r"'alpha' has shape \(1, 1472, 1, 1\), expected \(1, 1475, 1, 1\)"):
        load_dists(p)
    with pytest.raises(ConfigError, match="evaluate.dists_weights.*not found"):
        load_dists(tmp_path / "missing.pt")


def test_perceptual_metrics(learned):
    path, _ = learned
    assert perceptual_metrics(None, "") == {
        "one_minus_lpips": "unavailable: no weights path (evaluate.lpips_weights)",
        "one_minus_dists": "unavailable: no weights path (evaluate.dists_weights)"}
    m = perceptual_metrics(path, path)
    x, y = images((2, 1, 32, 32), noise=0.1)
    x, y = x.float(), y.float()
    for name in ("one_minus_lpips", "one_minus_dists"):
        assert (m[name](x, x) == 1).all() and (m[name](x, y) < 1).all()
        assert m[name](x.double(), y.double()).dtype == torch.float64  # float64 images are scored in float32
