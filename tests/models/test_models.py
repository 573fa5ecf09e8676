"""The sandwich GAN's networks (codesign/models): shapes, efficient attention, the PatchGAN receptive field,
the spectral (RFT) branch, ModelSpec validation, G2 weight sharing and the paper-size parameter count.

References: Sec. 4 of the paper (Eq. EffAttn; "Refinement with Coarse-to-Fine GAN") and the supplement's
"Net Architecture" (C-ERRA64..512 / DRRA512..64 UNet, E64-E128-E256-E512 PatchGAN with a 70 x 70 patch).
"""
from __future__ import annotations

import math

import pytest
import torch
import torch.nn as nn
from torch.utils.flop_counter import FlopCounterMode

from codesign.errors import ConfigError
from codesign.models import SGAN, SIZES, ModelSpec, build_sgan, coordinates, otf_from_kernel, parameter_count
from codesign.models.blocks import (EfficientAttention, FFTConvBlock, ResBlock, ResFFTBlock, SpectralBranch)
from codesign.models.discriminators import PatchDiscriminator, receptive_field
from codesign.models.sgan import Refiner
from codesign.models.unet import ResUNet


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _strip_instance_norms(module: nn.Module) -> None:
    """Replace every InstanceNorm by the identity (in place). Instance statistics couple every pixel of a map to
    every other, so the geometric receptive field of the convolutions can only be measured without them."""
    for name, child in module.named_children():
        if isinstance(child, nn.InstanceNorm2d):
            setattr(module, name, nn.Identity())
        else:
            _strip_instance_norms(child)


# ----------------------------------------------------------------------------------------------------------------
# 1. shapes
# ----------------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("p", [64, 50])
@pytest.mark.parametrize("variant", ["sgan_b", "sgan_e", "sgan_f"])
def test_sgan_output_shapes(variant, p):
    torch.manual_seed(0)
    spec = ModelSpec(variant=variant, size="tiny", fe_features=6)
    model = SGAN(spec)
    b = 2
    spec.check_input_size(p)
    sensor = torch.rand(b, 1, p, p)
    kernel = torch.rand(5, 5)
    out = model(sensor, otf_from_kernel(kernel / kernel.sum(), p))
    assert out["i_b"].shape == (b, 1, p, p)
    assert out["features"].shape == (b, 6, p, p)
    coarse, fine = out["b"]
    assert coarse.shape == (b, 1, p // 2, p // 2)
    assert fine.shape == (b, 1, p, p)
    for t in (out["i_b"], out["features"], coarse, fine):
        assert torch.isfinite(t).all()

    # D1 on (s, x, y, I_b): 3 stride-2 levels (p/8), then two k4 s1 p1 convolutions (-1 each)
    d_w = spec.d_widths
    score, feats = model.critic1(sensor, out["i_b"])
    assert score.shape == (b, 1, p // 8 - 2, p // 8 - 2)
    assert [tuple(f.shape) for f in feats] == [(b, d_w[0], p // 2, p // 2), (b, d_w[1], p // 4, p // 4),
                                               (b, d_w[2], p // 8, p // 8), (b, d_w[3], p // 8 - 1, p // 8 - 1)]
    # D2^L on b^L
    for level, img in enumerate(out["b"]):
        s = img.shape[-1]
        score, feats = model.d2[level](img)
        assert score.shape == (b, 1, s // 8 - 2, s // 8 - 2)
        assert len(feats) == len(d_w) and feats[-1].shape == (b, d_w[-1], s // 8 - 1, s // 8 - 1)


def test_variants_use_the_blocks_of_the_paper_table():
    """Table SGAN_G_and_D: SGAN-B/E: Res UNet + PatchGAN; SGAN-F: RFT UNet + FTC-PatchGAN; FE always a ResNet."""
    def kinds(m):
        return {type(x) for x in m.modules()}

    models = {v: SGAN(ModelSpec(variant=v, size="tiny")) for v in ("sgan_b", "sgan_e", "sgan_f")}
    for v in ("sgan_b", "sgan_e"):
        m = models[v]
        assert ResFFTBlock not in kinds(m) and FFTConvBlock not in kinds(m)
    f = models["sgan_f"]
    for g in (f.g1, f.g2):
        assert ResFFTBlock in kinds(g) and ResBlock not in kinds(g)
    for d in (f.d1, *f.d2):
        assert sum(isinstance(x, FFTConvBlock) for x in d.modules()) == len(f.spec.d_widths)
    assert ResBlock in kinds(f.gv) and ResFFTBlock not in kinds(f.gv)
    # SGAN-B and SGAN-E differ only in their losses
    assert parameter_count(models["sgan_b"]) == parameter_count(models["sgan_e"])
    assert parameter_count(models["sgan_f"]) > parameter_count(models["sgan_b"])


@pytest.mark.parametrize("block", ["res", "rft"])
@pytest.mark.parametrize("hw", [(37, 45), (51, 51), (33, 64), (20, 7)])
def test_resunet_keeps_odd_and_non_power_of_two_sizes(block, hw):
    torch.manual_seed(0)
    net = ResUNet(3, 2, 4, (8, 8), block=block, key_channels=4)
    x = torch.randn(1, 3, *hw)
    y = net(x)
    assert y.shape == (1, 2, *hw)
    assert torch.isfinite(y).all()


def test_coordinates_span_minus_one_to_one():
    like = torch.zeros(2, 1, 5, 9, dtype=torch.float64)
    c = coordinates(like)
    assert c.shape == (2, 2, 5, 9)
    assert torch.equal(c[0, 0, 3], torch.linspace(-1, 1, 9, dtype=torch.float64))   # x along the width
    assert torch.equal(c[1, 1, :, 4], torch.linspace(-1, 1, 5, dtype=torch.float64))  # y along the height


# ----------------------------------------------------------------------------------------------------------------
# 2. efficient self-attention
# ----------------------------------------------------------------------------------------------------------------

def _conv1x1(conv: nn.Conv2d, x: torch.Tensor) -> torch.Tensor:
    """(B, Cin, N) -> (B, Cout, N) by the conv's weights, written out."""
    return torch.einsum("oi,bin->bon", conv.weight[:, :, 0, 0], x) + conv.bias[None, :, None]


def _attention_reference(att: EfficientAttention, x: torch.Tensor):
    """E = softmax_rows(Q) [softmax_cols(K)^T V] (Q, K: N x d_k; V: N x C) evaluated through the explicit
    N x N matrix A = softmax_rows(Q) softmax_cols(K)^T, i.e. E = A V. Returns (E as (B, C, H, W), A)."""
    b, c, h, w = x.shape
    f = x.flatten(2)
    q = _conv1x1(att.query, f).transpose(1, 2)            # (B, N, d_k)
    k = _conv1x1(att.key, f).transpose(1, 2)              # (B, N, d_k)
    v = _conv1x1(att.value, f).transpose(1, 2)            # (B, N, C)
    q_rows = torch.softmax(q, dim=2)                      # each row (position) normalized over d_k
    k_cols = torch.softmax(k, dim=1)                      # each column (key channel) normalized over positions
    a = q_rows @ k_cols.transpose(1, 2)                   # (B, N, N)
    e = a @ v                                             # (B, N, C)
    return e.transpose(1, 2).reshape(b, c, h, w), a


ATTENTION_ATOL = 1e-12  # max |efficient attention - explicit N x N product| (benchmarks/bench_accuracy.py)


def _attention_case() -> tuple[EfficientAttention, torch.Tensor]:
    """(float64 attention with O(1) random weights and biases (global seed 0), input (2, 6, 5, 7))."""
    torch.manual_seed(0)
    att = EfficientAttention(6, key_channels=3).double()
    for m in (att.query, att.key, att.value):
        nn.init.normal_(m.weight, std=1.0)
        nn.init.normal_(m.bias, std=0.5)
    return att, torch.randn(2, 6, 5, 7, dtype=torch.float64)


def attention_error(case: tuple | None = None) -> float:
    """max |att.attend(x) - the explicit N x N softmax attention| (``case``: the _attention_case pair, computed
    when not given)."""
    att, x = _attention_case() if case is None else case
    return float((att.attend(x) - _attention_reference(att, x)[0]).detach().abs().max())


def test_efficient_attention_equals_the_explicit_n_by_n_product():
    att, x = _attention_case()
    ref, a = _attention_reference(att, x)
    # A is a proper attention matrix: non-negative rows that sum to one
    assert (a > 0).all()
    torch.testing.assert_close(a.sum(-1), torch.ones(2, 35, dtype=torch.float64), rtol=0, atol=1e-13)
    assert att.attend(x).shape == ref.shape and att.attend(x).dtype == ref.dtype
    assert attention_error((att, x)) <= ATTENTION_ATOL  # a NaN fails too
    # with a non-zero output projection R: f + R(E)
    nn.init.normal_(att.proj.weight)
    nn.init.normal_(att.proj.bias)
    expect = x + _conv1x1(att.proj, ref.flatten(2)).view_as(x)
    torch.testing.assert_close(att(x), expect, rtol=0, atol=1e-12)


def _flops(fn, *args) -> int:
    with FlopCounterMode(display=False) as counter:
        fn(*args)
    return counter.get_total_flops()


def test_efficient_attention_cost_is_linear_in_pixel_count():
    torch.manual_seed(0)
    att = EfficientAttention(8, key_channels=8)
    f = {n: _flops(att, torch.randn(1, 8, n, n)) for n in (8, 16, 32)}      # N, 4N, 16N pixels
    assert f[8] > 0
    assert f[16] / f[8] == pytest.approx(4.0, rel=0.01)
    assert f[32] / f[8] == pytest.approx(16.0, rel=0.01)
    # the counter does see quadratic cost: the explicit N x N form grows 16x for 4x the pixels
    g = {n: _flops(lambda x: _attention_reference(att, x), torch.randn(1, 8, n, n)) for n in (8, 16)}
    assert g[16] / g[8] > 10.0


def test_efficient_attention_is_identity_at_init_and_learns_gradually():
    torch.manual_seed(0)
    att = EfficientAttention(4, key_channels=2)
    assert torch.count_nonzero(att.proj.weight) == 0 and torch.count_nonzero(att.proj.bias) == 0
    x = torch.randn(2, 4, 6, 6)
    y = att(x)
    assert torch.equal(y, x)
    # R = 0: Q, K and V get no gradient yet, R does
    (y * torch.randn_like(y)).sum().backward()
    for m in (att.query, att.key, att.value):
        assert torch.count_nonzero(m.weight.grad) == 0
    assert att.proj.weight.grad.abs().sum() > 0
    # once R is non-zero the gradient reaches Q, K and V
    att.zero_grad()
    with torch.no_grad():
        att.proj.weight.normal_()
    y = att(x)
    (y * torch.randn_like(y)).sum().backward()
    for m in (att.query, att.key, att.value):
        assert m.weight.grad.abs().sum() > 1e-6
        assert torch.isfinite(m.weight.grad).all()


# ----------------------------------------------------------------------------------------------------------------
# 4. PatchGAN receptive field
# ----------------------------------------------------------------------------------------------------------------

def _expected_support(levels: int, o: int) -> tuple[int, int]:
    """Input interval [lo, hi] seen by output index o: (levels - 1) Conv(k4, s2, p1), one Conv(k4, s1, p1) and the
    Conv(k4, s1, p1) output layer (pix2pix), walked backwards."""
    layers = [(4, 2, 1)] * (levels - 1) + [(4, 1, 1), (4, 1, 1)]
    lo = hi = o
    for k, s, p in reversed(layers):
        lo, hi = lo * s - p, hi * s - p + k - 1
    return lo, hi


def test_receptive_field_formula():
    assert receptive_field(4) == 70            # the "70 x 70 patch" of the supplement
    assert receptive_field(3) == 34 and receptive_field(2) == 16    # pix2pix n_layers = 2 and 1
    for levels in (2, 3, 4, 5):
        lo, hi = _expected_support(levels, 10)
        assert hi - lo + 1 == receptive_field(levels)


@pytest.mark.parametrize("d_widths", [(4, 8), (4, 8, 8), (4, 8, 8, 8)])
def test_patch_discriminator_receptive_field_by_backprop(d_widths):
    torch.manual_seed(0)
    levels = len(d_widths)
    d = PatchDiscriminator(1, d_widths, attention=False, key_channels=8).double()
    _strip_instance_norms(d)
    size = 96
    x = torch.randn(1, 1, size, size, dtype=torch.float64, requires_grad=True)
    score, _ = d(x)
    oh, ow = score.shape[-2:]
    o = (oh // 2, ow // 2)
    score[0, 0, o[0], o[1]].backward()
    support = x.grad[0, 0] != 0
    (ylo, yhi), (xlo, xhi) = _expected_support(levels, o[0]), _expected_support(levels, o[1])
    assert 0 <= ylo and yhi < size and 0 <= xlo and xhi < size   # the patch lies inside the image
    expect = torch.zeros(size, size, dtype=torch.bool)
    expect[ylo: yhi + 1, xlo: xhi + 1] = True
    assert torch.equal(support, expect)
    assert int(support.sum()) == receptive_field(levels) ** 2
    if levels == 4:
        assert int(support.any(0).sum()) == int(support.any(1).sum()) == 70


def test_patch_discriminator_attention_makes_the_dependence_global():
    torch.manual_seed(0)
    d = PatchDiscriminator(1, (4, 8, 8, 8), attention=True, key_channels=4).double()
    _strip_instance_norms(d)
    size = 96
    x = torch.randn(1, 1, size, size, dtype=torch.float64, requires_grad=True)
    score, _ = d(x)
    score[0, 0, score.shape[-2] // 2, score.shape[-1] // 2].backward()
    assert int((x.grad != 0).sum()) == 70 * 70               # R = 0 at init: still the 70 x 70 patch
    x.grad = None
    with torch.no_grad():
        for m in d.modules():
            if isinstance(m, EfficientAttention):
                m.proj.weight.normal_()
    score, _ = d(x)
    score[0, 0, score.shape[-2] // 2, score.shape[-1] // 2].backward()
    assert (x.grad != 0).all()


# ----------------------------------------------------------------------------------------------------------------
# 5. RFT: the spectral branch
# ----------------------------------------------------------------------------------------------------------------

def _make_complex_linear(branch: SpectralBranch, a: torch.Tensor, b: torch.Tensor, z_max: float = 0.0) -> None:
    """Set the branch to Y_o = sum_i (a_oi + i b_oi) X_i per frequency (a complex-linear map of rfft2(x)).

    W = [[a, -b], [b, a]] acting on [Re X; Im X]. The ReLU between the two 1x1 convolutions is made inactive
    exactly when there are enough channels (cout >= 2 cin: conv1 = [I; -I], conv2 = [W, -W], using
    relu(z) - relu(-z) = z); otherwise conv1 = W plus a bias c > |W z| (bounded by W's row sums times max |X|,
    which a circular shift leaves unchanged) and conv2 = I minus c."""
    w = torch.cat([torch.cat([a, -b], 1), torch.cat([b, a], 1)], 0)        # (2 cout, 2 cin)
    two_out, two_in = w.shape
    conv1, conv2 = branch.body[0], branch.body[2]
    with torch.no_grad():
        if two_out >= 2 * two_in:
            eye = torch.eye(two_in)
            w1 = torch.zeros(two_out, two_in)
            w1[: 2 * two_in] = torch.cat([eye, -eye], 0)
            w2 = torch.zeros(two_out, two_out)
            w2[:, : 2 * two_in] = torch.cat([w, -w], 1)
            conv1.weight.copy_(w1[:, :, None, None])
            conv1.bias.zero_()
            conv2.weight.copy_(w2[:, :, None, None])
            conv2.bias.zero_()
        else:
            c = 1.01 * float(w.abs().sum(1).max()) * z_max + 1e-3
            conv1.weight.copy_(w[:, :, None, None])
            conv1.bias.fill_(c)
            conv2.weight.copy_(torch.eye(two_out)[:, :, None, None])
            conv2.bias.fill_(-c)


def _complex_linear_reference(x: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    x = x.double()
    spec = torch.fft.rfft2(x)
    y = torch.einsum("oi,bihw->bohw", torch.complex(a.double(), b.double()), spec)
    return torch.fft.irfft2(y, s=x.shape[-2:])


def test_spectral_branch_identity_round_trip_on_odd_sizes():
    x = torch.randn(2, 3, 9, 10, generator=_gen(1))
    branch = SpectralBranch(3, 3)
    z_max = float(torch.fft.rfft2(x, norm="ortho").abs().max())
    _make_complex_linear(branch, torch.eye(3), torch.zeros(3, 3), z_max)
    torch.testing.assert_close(branch(x), x, rtol=0, atol=1e-4)


def test_spectral_branch_complex_linear_map_and_shift_equivariance():
    g = _gen(2)
    x = torch.rand(1, 2, 16, 12, generator=g)
    a, b = torch.randn(4, 2, generator=g), torch.randn(4, 2, generator=g)
    branch = SpectralBranch(2, 4)
    _make_complex_linear(branch, a, b)                 # exact: no bias, the ReLU pair cancels
    y = branch(x)
    torch.testing.assert_close(y.double(), _complex_linear_reference(x, a, b), rtol=0, atol=1e-5)
    # circular shifts multiply each frequency by a phase; a complex-linear per-frequency map commutes with that
    shift = (3, 5)
    y_shifted = branch(torch.roll(x, shift, dims=(-2, -1)))
    torch.testing.assert_close(y_shifted, torch.roll(y, shift, dims=(-2, -1)), rtol=0, atol=1e-5)
    # ...while a zero-padded spatial convolution does not
    conv = nn.Conv2d(2, 3, 3, padding=1)
    diff = conv(torch.roll(x, shift, dims=(-2, -1))) - torch.roll(conv(x), shift, dims=(-2, -1))
    assert diff.abs().max() > 1e-2


def test_spectral_branch_with_generic_weights_is_global():
    """The spectral branch sees the whole image: one output pixel depends on every input pixel."""
    torch.manual_seed(0)
    branch = SpectralBranch(2, 2).double()
    x = torch.randn(1, 2, 12, 12, dtype=torch.float64, requires_grad=True)
    branch(x)[0, 0, 0, 0].backward()
    assert (x.grad != 0).all()


def test_res_fft_block_adds_identity_spatial_and_spectral_branches():
    x = torch.randn(1, 3, 11, 8, generator=_gen(3))
    block = ResFFTBlock(3)
    with torch.no_grad():   # spatial branch off: the affine of its last InstanceNorm to zero
        block.spatial[-1].weight.zero_()
        block.spatial[-1].bias.zero_()
    z_max = float(torch.fft.rfft2(x, norm="ortho").abs().max())
    _make_complex_linear(block.spectral, torch.eye(3), torch.zeros(3, 3), z_max)
    torch.testing.assert_close(block(x), torch.relu(2 * x), rtol=0, atol=2e-4)
    # a quarter-turn of every frequency (multiplying by i): x + H{x} where H is a linear shift-invariant map
    _make_complex_linear(block.spectral, torch.zeros(3, 3), torch.eye(3), z_max)
    ref = torch.relu(x.double() + _complex_linear_reference(x, torch.zeros(3, 3), torch.eye(3)))
    torch.testing.assert_close(block(x).double(), ref, rtol=0, atol=2e-4)
    shift = (4, 3)
    torch.testing.assert_close(block(torch.roll(x, shift, (-2, -1))), torch.roll(block(x), shift, (-2, -1)),
                               rtol=0, atol=1e-5)


def test_spectral_branch_keeps_float64():
    x = torch.randn(1, 2, 9, 10, dtype=torch.float64, generator=_gen(4))
    branch = SpectralBranch(2, 2).double()
    z_max = float(torch.fft.rfft2(x, norm="ortho").abs().max())
    _make_complex_linear(branch, torch.eye(2), torch.zeros(2, 2), z_max)
    torch.testing.assert_close(branch(x), x, rtol=0, atol=1e-12)


def test_fft_conv_block_shapes_on_odd_sizes():
    torch.manual_seed(0)
    for size in (17, 24):
        x = torch.randn(1, 2, size, size)
        assert FFTConvBlock(2, 4, stride=2)(x).shape == (1, 4, size // 2, size // 2)
        assert FFTConvBlock(2, 4, stride=1)(x).shape == (1, 4, size - 1, size - 1)   # as Conv(k4, s1, p1)


# ----------------------------------------------------------------------------------------------------------------
# 6. ModelSpec
# ----------------------------------------------------------------------------------------------------------------

def test_paper_size_preset_matches_the_supplement():
    spec = ModelSpec(size="paper")
    assert spec.stem_width == 64
    assert spec.widths == (64, 128, 256, 512, 512, 512, 512)       # C-ERRA64-...-ERRA512 x 4
    assert spec.d_widths == (64, 128, 256, 512)                    # E64-E128-E256-E512
    assert spec.fe_features == 16 and spec.fe_kernel == 5 and spec.key_channels == 8
    assert SIZES["paper"]["widths"] == spec.widths
    assert ModelSpec(size="tiny", widths=[4, 6, 8]).widths == (4, 6, 8)      # explicit widths override


def test_model_spec_errors():
    with pytest.raises(ConfigError) as err:
        ModelSpec(variant="sgan_x")
    assert "model.variant" in str(err.value) and "sgan_b, sgan_e, sgan_f" in str(err.value)
    assert err.value.key == "model.variant" and err.value.value == "sgan_x"
    with pytest.raises(ConfigError) as err:
        ModelSpec(fe_kernel=4)
    assert str(err.value) == "model.fe_kernel = 4: must be odd (same-size convolution)"
    with pytest.raises(ConfigError) as err:
        build_sgan({"variant": "sgan_b", "bogus": 1})
    assert err.value.key == "model.bogus" and "unknown key" in str(err.value)
    with pytest.raises(ConfigError):
        ModelSpec(size="huge")
    with pytest.raises(ConfigError):
        ModelSpec(d_widths=[8])          # a critic needs at least two levels
    with pytest.raises(ConfigError):
        ModelSpec(attention="yes")
    # the loss block belongs to the restorer (its objective): validated with it, and kept
    with pytest.raises(ConfigError) as err:
        build_sgan({"variant": "sgan_e", "size": "tiny", "loss": {"l1": 1.0}})
    assert err.value.key == "model.loss.l1" and "unknown key" in str(err.value)
    assert build_sgan({"variant": "sgan_e", "size": "tiny", "loss": {"vgg": 3.0}}).weights.vgg == 3.0


def test_check_input_size_rejects_odd_and_small_grids():
    spec = ModelSpec(size="tiny")
    with pytest.raises(ConfigError, match="even"):
        spec.check_input_size(50 + 1)
    with pytest.raises(ConfigError, match="too small"):
        spec.check_input_size(16)


def _smallest_accepted(spec: ModelSpec) -> int:
    for p in range(2, 1024, 2):
        try:
            spec.check_input_size(p)
        except ConfigError:
            continue
        return p
    raise AssertionError("no size accepted")


def test_check_input_size_accepts_only_sizes_the_critics_can_take():
    spec = ModelSpec(size="tiny")
    p = _smallest_accepted(spec)
    d = PatchDiscriminator(1, spec.d_widths, attention=False, key_channels=spec.key_channels)
    score, _ = d(torch.zeros(1, 1, p // 2, p // 2))
    assert score.numel() > 0


def test_check_input_size_accepts_only_sizes_the_generator_can_take():
    spec = ModelSpec(size="paper")
    p = _smallest_accepted(spec)
    with torch.device("meta"):
        g2 = Refiner(spec)
        coarse, fine = g2(torch.zeros(1, spec.fe_features, p, p))
    assert coarse.shape[-1] == p // 2 and fine.shape[-1] == p


# ----------------------------------------------------------------------------------------------------------------
# 7. G2 weight sharing across scales
# ----------------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("coarse_to_fine", [True, False])
def test_refiner_shares_body_and_keeps_one_head_per_scale(coarse_to_fine):
    torch.manual_seed(0)
    spec = ModelSpec(size="tiny", fe_features=3, coarse_to_fine=coarse_to_fine)
    g2 = Refiner(spec)
    # the heads are distinct modules with distinct parameters; two layers each (paper: "the first two input layers")
    h0, h1 = g2.heads
    assert h0 is not h1 and len(h0) == len(h1) == spec.g2_head_layers == 2
    assert not ({id(p) for p in h0.parameters()} & {id(p) for p in h1.parameters()})
    assert h1[0][0].in_channels == 3 + int(coarse_to_fine)
    skip = spec.fe_features + 1  # the linear 1x1 readout of the features (g2_linear_skip)
    assert parameter_count(g2) == parameter_count(h0) + parameter_count(h1) + parameter_count(g2.body) + skip

    feats = torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        g2.body.out.weight.normal_(std=0.1)  # the output layer starts at zero: make the body's effect visible
        c0, f0 = g2(feats)

        def outputs_after(param):
            saved = param.clone()
            param.add_(torch.randn_like(param))
            c, f = g2(feats)
            param.copy_(saved)
            return (c - c0).abs().max().item(), (f - f0).abs().max().item()

        dc, df = outputs_after(g2.body.out.weight)                 # shared body: both scales change
        assert dc > 1e-4 and df > 1e-4
        dc, df = outputs_after(g2.body.encoder[0].resample[0].weight)
        assert dc > 1e-4 and df > 1e-4
        dc, df = outputs_after(h0[0][0].weight)                   # coarse head
        assert dc > 1e-4
        if coarse_to_fine:
            assert df > 1e-4                                      # fine head sees the upsampled coarse estimate
        else:
            assert df == 0.0
        dc, df = outputs_after(h1[0][0].weight)                   # fine head: never the coarse output
        assert dc == 0.0 and df > 1e-4


# ----------------------------------------------------------------------------------------------------------------
# 8. parameter count at paper size, derived from the layer listing
# ----------------------------------------------------------------------------------------------------------------

def _conv(cin, cout, k):
    return cin * cout * k * k + cout


def _norm(c):
    return 2 * c                       # affine InstanceNorm: scale and shift


def _res(c, k=3):                      # R: two Conv-IN with the skip
    return 2 * (_conv(c, c, k) + _norm(c))


def _attn(c, dk=8):                    # A: Q, K (d_k channels), V and R (C channels), all 1x1
    return 2 * _conv(c, dk, 1) + 2 * _conv(c, c, 1)


def _xrra(cin, cout):                  # ERRA / DRRA: E or D (k4), R, R, A
    return _conv(cin, cout, 4) + _norm(cout) + 2 * _res(cout) + _attn(cout)


def _paper_unet(in_channels, head_layers=1):
    """C7 64 - ERRA64-128-256-512-512-512-512 - DRRA512-512-512-512-256-128-64 - Conv7 -> 1; each decoder block
    after the first takes the previous decoder output concatenated with the encoder output of its resolution;
    the output conv takes [last decoder output, C output]."""
    enc = [64, 128, 256, 512, 512, 512, 512]
    dec = [512, 512, 512, 512, 256, 128, 64]
    n = 64 * in_channels * 49 + 64 + _norm(64) + (head_layers - 1) * (_conv(64, 64, 3) + _norm(64))
    cin = 64
    for w in enc:
        n += _xrra(cin, w)
        cin = w
    for i, w in enumerate(dec):
        cin = enc[-1] if i == 0 else dec[i - 1] + enc[len(enc) - 1 - i]
        n += _xrra(cin, w)
    return n + _conv(64 + 64, 1, 7)


def test_paper_size_parameter_count():
    spec = ModelSpec(variant="sgan_b", size="paper")
    with torch.device("meta"):
        model = SGAN(spec)
    g1 = _paper_unet(3)
    fe = _conv(1, 16, 5) + _norm(16) + 3 * _res(16, 5)
    gv = fe + 16                                                    # + gamma (one rho per feature)
    g2_body = _paper_unet(16) - (_conv(16, 64, 7) + _norm(64))     # without its head
    g2 = g2_body + (_conv(16, 64, 7) + _norm(64) + _conv(64, 64, 3) + _norm(64)) \
        + (_conv(17, 64, 7) + _norm(64) + _conv(64, 64, 3) + _norm(64)) + _conv(16, 1, 1)  # + linear skip
    d_levels = [(1, 64), (64, 128), (128, 256), (256, 512)]
    d2 = sum(_conv(ci, co, 4) + (_norm(co) if i > 0 else 0) + _attn(co) for i, (ci, co) in enumerate(d_levels)) \
        + _conv(512, 1, 4)
    d1 = d2 + 3 * 64 * 16                                           # D1 sees (s, x, y, I_b): 3 more input channels
    assert parameter_count(model.g1) == g1
    assert parameter_count(model.gv) == gv
    assert parameter_count(model.g2) == g2
    assert parameter_count(model.d1) == d1
    assert parameter_count(model.d2) == 2 * d2
    total = parameter_count(model.g1) + parameter_count(model.gv) + parameter_count(model.g2)
    assert total == g1 + gv + g2
    assert 130e6 < g1 < 140e6                                       # ~135 M per residual UNet
    assert math.isclose(total / 1e6, 270.8, rel_tol=0.01)
