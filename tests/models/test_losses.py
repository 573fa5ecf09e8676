"""SGAN training losses: exact zeros, closed forms, WGAN-GP on linear critics, VGG loss from a user file."""
from __future__ import annotations

import math

import pytest
import torch
import torch.nn as nn

from codesign.errors import ConfigError
from codesign.models.losses import (VGGPerceptualLoss, build_vgg_loss, charbonnier, critic_loss, feature_matching_loss,
                             fft_loss, generator_adv_loss, gradient_penalty)
from codesign.models.vgg import ImageNetInput, extract, vgg19_features

from .test_vgg import random_state_dict


def pair(shape=(2, 1, 8, 10), seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(shape, generator=g, dtype=dtype), torch.rand(shape, generator=g, dtype=dtype)


def test_charbonnier():
    x, y = pair()
    assert charbonnier(x, x).item() == 0.0
    eps = 1e-6
    ref = ((x - y) ** 2 + eps).sqrt().mean() - math.sqrt(eps)
    torch.testing.assert_close(charbonnier(x, y, eps), ref, rtol=1e-12, atol=0)
    assert charbonnier(x, y) > 0
    # gradient of the paper's sqrt(|d|^2 + eps): the subtracted constant changes nothing
    x.requires_grad_(True)
    (g,) = torch.autograd.grad(charbonnier(x, y, eps), x)
    torch.testing.assert_close(g, (x - y).detach() / (((x - y).detach() ** 2 + eps).sqrt() * x.numel()))
    # float32 near zero: no cancellation (sqrt(d^2 + eps) - sqrt(eps) would round to 0 for d = 1e-5)
    a = torch.zeros(4)
    torch.testing.assert_close(charbonnier(a + 1e-5, a), torch.tensor(1e-10 / (2 * 1e-3)), rtol=1e-4, atol=0)


def test_wgan_terms():
    real, fake = torch.tensor([1.0, 3.0]), torch.tensor([-1.0, 0.5])
    assert critic_loss(real, fake).item() == pytest.approx(-0.25 - 2.0)
    assert critic_loss(real, real).item() == 0.0
    assert generator_adv_loss(fake).item() == pytest.approx(0.25)
    # multiscale: sum over scales
    assert critic_loss([real, real * 2], [fake, fake]).item() == pytest.approx(-2.25 + (-0.25 - 4.0))
    assert generator_adv_loss([fake, torch.ones(3, 1, 2, 2)]).item() == pytest.approx(0.25 - 1.0)
    with pytest.raises(ValueError):
        critic_loss([real], [fake, fake])


class Linear(nn.Module):
    """D(z) = <w, z> per sample (flattened); returns (output, features) like the project's critics."""

    def __init__(self, shape, seed):
        super().__init__()
        self.w = nn.Parameter(torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64))

    def forward(self, z):
        return (z * self.w).flatten(1).sum(1, keepdim=True), [z]


GP_LINEAR_RTOL = 1e-12  # |gradient penalty / (||w|| - 1)^2 - 1| (benchmarks/bench_accuracy.py reports it)


def _linear_penalty():
    """(linear critic, ||w||, its WGAN gradient penalty on a (3, 2, 5, 4) pair, interpolation seed 0)."""
    real, fake = pair((3, 2, 5, 4))
    critic = Linear((2, 5, 4), seed=1)
    gp = gradient_penalty(critic, real, fake, generator=torch.Generator().manual_seed(0))
    return critic, critic.w.norm(), gp


def gradient_penalty_linear_error(case: tuple | None = None) -> float:
    """|GP / (||w|| - 1)^2 - 1| for the linear critic D(z) = <w, z>, whose gradient is w everywhere (``case``: the
    _linear_penalty triple, computed when not given)."""
    _, norm, gp = _linear_penalty() if case is None else case
    return abs(float(gp.detach()) / float(((norm - 1) ** 2).detach()) - 1)


def test_gradient_penalty_linear_critic():
    case = _linear_penalty()
    critic, norm, gp = case
    assert gp.shape == norm.shape and gp.dtype == norm.dtype
    assert gradient_penalty_linear_error(case) <= GP_LINEAR_RTOL  # a NaN fails too
    # backpropagates into the critic: d/dw (||w|| - 1)^2 = 2 (||w|| - 1) w / ||w||
    gp.backward()
    torch.testing.assert_close(critic.w.grad, (2 * (norm - 1) * critic.w / norm).detach(), rtol=1e-10, atol=0)


def test_gradient_penalty_with_condition():
    real, fake = pair((2, 1, 6, 6))
    cond = torch.rand(2, 3, 6, 6, dtype=torch.float64)
    critic = Linear((4, 6, 6), seed=2)  # sees [cond (3 ch), x (1 ch)]: the gradient w.r.t. x is w[3]
    gp = gradient_penalty(critic, real, fake, cond=cond)
    torch.testing.assert_close(gp, (critic.w[3].norm() - 1) ** 2, rtol=1e-12, atol=0)


def test_gradient_penalty_patch_critic_uses_mean():
    # a 1x1 linear conv critic outputs a patch map; the sample's critic value is its mean, so grad = w / (H W) at
    # every pixel and ||grad|| = ||w|| / sqrt(H W)
    conv = nn.Conv2d(2, 1, 1, bias=True).double()
    real, fake = pair((2, 2, 4, 6))
    gp = gradient_penalty(conv, real, fake)
    torch.testing.assert_close(gp, (conv.weight.norm() / math.sqrt(24) - 1) ** 2, rtol=1e-12, atol=0)


def test_gradient_penalty_reproducible():
    critic = nn.Sequential(nn.Conv2d(1, 4, 3), nn.Tanh(), nn.Conv2d(4, 1, 3)).double()
    real, fake = pair((4, 1, 8, 8))
    a = gradient_penalty(critic, real, fake, generator=torch.Generator().manual_seed(5))
    b = gradient_penalty(critic, real, fake, generator=torch.Generator().manual_seed(5))
    c = gradient_penalty(critic, real, fake, generator=torch.Generator().manual_seed(6))
    assert a.item() == b.item() and a.item() != c.item() and a.item() > 0


def test_feature_matching():
    r = [[torch.zeros(2, 3, 4, 4), torch.zeros(2, 5, 2, 2)], [torch.zeros(2, 3, 2, 2), torch.zeros(2, 5, 1, 1)]]
    f = [[t + v for t in s] for s, v in zip(r, (1.0, 3.0))]
    assert feature_matching_loss(r, r).item() == 0.0
    # per scale: (sum over its 2 layers of mean |diff|) / 2; scales summed
    assert feature_matching_loss(r, f).item() == pytest.approx((1 + 1) / 2 + (3 + 3) / 2)
    assert feature_matching_loss(r[0], f[0]).item() == pytest.approx(1.0)  # a flat list is one scale
    real = torch.rand(1, 2, 3, 3, requires_grad=True)
    fake = torch.rand(1, 2, 3, 3, requires_grad=True)
    feature_matching_loss([real], [fake]).backward()
    assert real.grad is None and fake.grad is not None


@pytest.mark.parametrize("h,w", [(6, 8), (5, 7)])
def test_fft_loss_closed_form(h, w):
    x, y = pair((2, 1, h, w))
    assert fft_loss(x, x).item() == 0.0
    c = -0.3
    # constant offset: only the DC coefficient is nonzero, |c| sqrt(HW) (ortho); mean over H x (W//2+1) coefficients
    torch.testing.assert_close(fft_loss(x + c, x), torch.tensor(abs(c) * math.sqrt(h * w) / (h * (w // 2 + 1)),
                                                                dtype=torch.float64), rtol=1e-12, atol=1e-15)
    assert fft_loss(x, y) > 0
    xg = x.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(fft_loss(xg, x), xg)  # |0| has a finite (zero) subgradient
    assert torch.isfinite(g).all()


@pytest.fixture(scope="module")
def vgg19_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("vgg_loss") / "vgg19.pth"
    torch.save(random_state_dict(vgg19_features, seed=3), path)
    return path


def test_vgg_loss(vgg19_path):
    assert build_vgg_loss(None, None) == (None, "off: no VGG19 weights configured (model.loss.vgg_weights)")
    assert build_vgg_loss("", None)[0] is None
    loss, status = build_vgg_loss(str(vgg19_path), None)
    assert status == f"on: {vgg19_path}"
    assert loss.indices == [3, 8, 17, 26, 35] and len(loss.features) == 36  # stops at relu5_4
    x, y = pair((2, 1, 32, 32), dtype=torch.float32)
    assert loss(x, x).item() == 0.0
    value = loss(x, y)
    assert value > 0
    fx = extract(loss.features, ImageNetInput()(x), loss.indices)
    fy = extract(loss.features, ImageNetInput()(y), loss.indices)
    ref = sum((a - b).abs().mean() for a, b in zip(fx, fy)) / 5
    torch.testing.assert_close(value, ref, rtol=1e-5, atol=0)
    xg = x.clone().requires_grad_(True)
    loss.train()(xg, y).backward()
    assert xg.grad.abs().sum() > 0 and all(p.grad is None for p in loss.parameters())
    assert not loss.features.training
    shallow = VGGPerceptualLoss(loss.features, layers=["relu1_2", 8])
    assert shallow.indices == [3, 8] and len(shallow.features) == 9


def test_vgg_loss_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="model.loss.vgg_weights.*nope.pth.*not found"):
        build_vgg_loss(tmp_path / "nope.pth", None)


class HalfSquare(nn.Module):
    """D(z) = 0.5 ||z||^2 per sample: its gradient is z itself, so the penalty sees where x~ was taken."""

    def forward(self, z):
        return 0.5 * z.flatten(1).square().sum(1, keepdim=True), [z]


def test_gradient_penalty_samples_on_the_straight_line():
    real, fake = pair((4, 1, 3, 3))
    gen = torch.Generator().manual_seed(5)
    gp = gradient_penalty(HalfSquare(), real, fake, generator=torch.Generator().manual_seed(5))
    eps = torch.rand((4, 1, 1, 1), generator=gen, dtype=torch.float64)  # the same draws
    x = eps * real + (1 - eps) * fake
    expected = ((x.flatten(1).norm(dim=1) - 1) ** 2).mean()
    torch.testing.assert_close(gp, expected, rtol=1e-12, atol=0)
