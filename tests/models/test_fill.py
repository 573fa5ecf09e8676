"""The sensor image's hole filling (saturated laser footprint, zero padding) and the SGAN's residual options that
start from it: valid pixels untouched, holes filled from their surroundings, exact identities at initialization."""
from __future__ import annotations

import math

import pytest
import torch

from codesign.errors import ConfigError
from codesign.models import SGAN, ModelSpec, otf_from_kernel
from codesign.models.fill import push_pull_fill, replicate_outside_field, valid_pixels
from codesign.models.sandwich import coordinates, downsample2
from codesign.models.wiener import classical_wiener
from codesign.experiments.resume import _with_added_keys
from codesign.train.optim import init_weights


def _capture(p: int = 48, n: int = 32) -> torch.Tensor:
    """A padded normalized capture: a smooth ramp inside the n x n field, a saturated disc, zeros outside."""
    y, x = torch.meshgrid(torch.linspace(0, 1, p), torch.linspace(0, 1, p), indexing="ij")
    s = 0.2 + 0.5 * x + 0.1 * y
    r2 = (x - 0.5) ** 2 + (y - 0.5) ** 2
    s = torch.where(r2 < 0.01, torch.ones_like(s), s)
    m = (p - n) // 2
    field = torch.zeros(p, p, dtype=torch.bool)
    field[m:m + n, m:m + n] = True
    return torch.where(field, s, torch.zeros_like(s))[None, None].double()


def test_valid_pixels_are_the_field_below_saturation():
    s = _capture()
    v = valid_pixels(s)
    assert not bool(v[s == 0].any()) and not bool(v[s == 1].any()) and bool(v[(s > 0) & (s < 1)].all())


def test_fill_keeps_valid_pixels_and_continues_a_ramp_into_the_holes():
    s = _capture()
    v = valid_pixels(s)
    out = push_pull_fill(s, v)
    assert torch.equal(out[v], s[v])  # measured pixels are returned exactly
    holes = out[~v]
    assert bool(torch.isfinite(holes).all())
    lo, hi = float(s[v].min()), float(s[v].max())
    assert lo - 1e-12 <= float(holes.min()) and float(holes.max()) <= hi + 1e-12  # an average: no overshoot
    # inside the saturated disc the ramp (0.2 + 0.5 x + 0.1 y, ~0.5 at the centre) is continued, not the 1.0
    p = s.shape[-1]
    centre = out[0, 0, p // 2 - 2:p // 2 + 2, p // 2 - 2:p // 2 + 2]
    assert float((centre - 0.5).abs().max()) < 0.08


def test_fill_of_a_constant_is_the_constant_and_of_nothing_valid_is_the_input():
    c = torch.full((2, 1, 20, 20), 0.3, dtype=torch.float64)
    v = torch.rand(2, 1, 20, 20, generator=torch.Generator().manual_seed(0)) > 0.7
    assert torch.allclose(push_pull_fill(c, v), c, atol=1e-15)
    x = torch.rand(1, 1, 9, 9, dtype=torch.float64)
    assert torch.equal(push_pull_fill(x, torch.zeros_like(x, dtype=torch.bool)), x)


def test_fill_gradcheck():
    s = _capture(16, 10).requires_grad_(True)
    v = valid_pixels(s.detach())
    assert torch.autograd.gradcheck(lambda t: push_pull_fill(t, v), (s,))


@pytest.mark.parametrize("base", ["sensor", "filled"])
def test_with_both_residual_paths_the_untrained_sandwich_returns_its_base(base):
    """G1's and G2's output convolutions start at zero: I_b^ is the base and the restoration is I_b^ exactly."""
    torch.manual_seed(0)
    model = SGAN(ModelSpec(size="tiny", fe_features=4, g2_residual=True, g1_base=base))
    init_weights(model)
    s = _capture().float()
    k = torch.rand(5, 5)
    out = model(s, otf_from_kernel(k / k.sum(), s.shape[-1]))
    want = s if base == "sensor" else push_pull_fill(s, valid_pixels(s))
    assert torch.equal(out["i_b"], want) and torch.equal(out["restored"], want)


def test_checkpoints_from_before_the_residual_options_read_as_trained():
    saved = {"model": {"kind": "sgan", "variant": "sgan_b"}, "optics": {"focal_n": 160}}
    model = _with_added_keys(saved)["model"]
    assert model["g2_residual"] is False and model["g1_base"] == "sensor" and model["g2_base"] == "i_b"
    assert model["g2_base_pad"] == "filled"  # what every checkpoint before the option computed
    other = {"model": {"kind": "wiener_unet"}}
    assert _with_added_keys(other)["model"] == {"kind": "wiener_unet"}


def test_g1_base_is_checked():
    with pytest.raises(Exception, match="model.g1_base"):
        ModelSpec(g1_base="wiener")


def _unit_dc_wiener(x: torch.Tensor, otf: torch.Tensor, nsr: float) -> torch.Tensor:
    """The classical Wiener filter scaled to unit DC gain (a flat image keeps its level): H(0) = 1 here."""
    assert abs(complex(otf[0, 0]) - 1) < 1e-6
    return classical_wiener(x, otf, nsr) * (1 + nsr)


def test_with_a_wiener_base_the_untrained_sandwich_returns_the_classical_pipeline():
    """model.g2_base=wiener: G2 corrects the Wiener deconvolution of I_b^ (the learned nsr at its start value) at unit
    DC gain, so the untrained network is the classical pipeline (the evaluation's g1_wiener) up to that gain, a
    flat image keeps its level at any nsr; the nsr gets a gradient."""
    torch.manual_seed(0)
    model = SGAN(ModelSpec(size="tiny", fe_features=4, g2_residual=True, g1_base="filled", g2_base="wiener",
                           g2_base_nsr=0.05))
    init_weights(model)
    s = _capture().float()
    k = torch.rand(5, 5)
    otf = otf_from_kernel(k / k.sum(), s.shape[-1])
    out = model(s, otf)
    filled = push_pull_fill(s, valid_pixels(s))
    assert torch.equal(out["i_b"], filled)
    assert torch.allclose(out["restored"], _unit_dc_wiener(filled, otf, 0.05), atol=1e-6)
    assert torch.equal(out["base"], out["restored"])  # the untrained correction is zero: the output is the base
    flat = torch.full_like(s, 0.4)
    with torch.no_grad():
        for nsr in (100.0, 0.05):  # a flat image keeps its level at any nsr (classical Wiener: 0.4 / (1 + nsr))
            model.g2.log_nsr.fill_(math.log(nsr))
            torch.testing.assert_close(model.g2.base(flat, otf), flat, atol=1e-5, rtol=0)
    out["restored"].square().mean().backward()
    assert model.g2.log_nsr.grad is not None and float(model.g2.log_nsr.grad.abs()) > 0


def test_replicate_outside_field_keeps_the_field_and_repeats_its_border():
    s = _capture(p=12, n=6)  # field rows and columns 3..8
    x = torch.randn(2, 1, 12, 12, dtype=torch.float64, requires_grad=True)
    out = replicate_outside_field(x, s.expand(2, 1, 12, 12))
    assert torch.equal(out[..., 3:9, 3:9], x[..., 3:9, 3:9])
    assert torch.equal(out[..., 0, 5], x[..., 3, 5]) and torch.equal(out[..., 11, 11], x[..., 8, 8])
    assert torch.equal(out[..., 5, :3], x[..., 5, 3:4].expand(2, 1, 3))
    out.sum().backward()  # every canvas pixel's gradient lands on the field pixel it copies
    assert float(x.grad.sum()) == 2 * 144 and float(x.grad[..., 0, 0].abs().sum()) == 0
    assert float(x.grad[0, 0, 3, 3]) == 16  # the corner pixel fills its 4 x 4 corner block
    full = torch.ones(1, 1, 12, 12, dtype=torch.float64)
    assert torch.equal(replicate_outside_field(x, full), x)  # no padding: unchanged
    assert torch.equal(replicate_outside_field(x, torch.zeros_like(full)), x)  # no field: unchanged


def test_g2_base_pad_replicate_deconvolves_the_replicated_field():
    """model.g2_base_pad=replicate: the untrained sandwich (its output is its base) returns the unit-DC Wiener
    deconvolution of I_b^ with the field's border replicated into the padding; the default keeps the filled I_b^."""
    torch.manual_seed(0)
    common = dict(size="tiny", fe_features=4, g2_residual=True, g1_base="filled", g2_base="wiener", g2_base_nsr=0.05)
    s = _capture().float()
    k = torch.rand(5, 5)
    otf = otf_from_kernel(k / k.sum(), s.shape[-1])
    outs = {}
    for pad in ("filled", "replicate"):
        model = SGAN(ModelSpec(**common, g2_base_pad=pad))
        init_weights(model)
        outs[pad] = model(s, otf)
    filled = push_pull_fill(s, valid_pixels(s))
    assert torch.equal(outs["replicate"]["i_b"], filled)  # G1's output is the same; only the base's input differs
    torch.testing.assert_close(outs["replicate"]["base"],
                               _unit_dc_wiener(replicate_outside_field(filled, s), otf, 0.05), atol=1e-6, rtol=0)
    torch.testing.assert_close(outs["filled"]["base"], _unit_dc_wiener(filled, otf, 0.05), atol=1e-6, rtol=0)
    assert float((outs["replicate"]["base"] - outs["filled"]["base"]).detach().abs().max()) > 1e-3
    with pytest.raises(ConfigError, match="model.g2_base_pad = 'zero': must be one of filled, replicate"):
        ModelSpec(**common, g2_base_pad="zero")


def _gated_pair(options: dict, randomized: str):
    """(model, [clean; lasered] sensor batch, OTF, (clean, lasered)): a tiny laser-gated SGAN with a Wiener base
    whose ``randomized`` generator (g1 or g2) has non-zero weights (a correction for the gate to scale; learned
    scalars as configured), the lasered capture and the same with its saturated pixels set to 0.5."""
    torch.manual_seed(0)
    model = SGAN(ModelSpec(size="tiny", fe_features=4, g2_residual=True, g1_base="filled", g2_base="wiener",
                           laser_gate=True, laser_gate_f0=0.01, **options))
    init_weights(model)
    for p in getattr(model, randomized).parameters():
        if p.dim() > 0:
            torch.nn.init.normal_(p, std=0.05)
    lasered = _capture().float()
    clean = torch.where(lasered >= 1, torch.full_like(lasered, 0.5), lasered)
    k = torch.rand(5, 5)
    return model, torch.cat([clean, lasered]), otf_from_kernel(k / k.sum(), lasered.shape[-1]), (clean, lasered)

def test_g2_gate_leaves_an_unlasered_image_at_its_base_and_corrects_a_lasered_one():
    """model.g2_gate: G2's correction times the presence p, so an image without saturated pixels leaves the network
    as its base (the classical pipeline's image) whatever G2's weights, and a lasered one gets p x the correction;
    refused without the laser gate."""
    model, s, otf, _ = _gated_pair(dict(g2_gate=True), "g2")
    out = model(s, otf)
    presence = model.g2.laser_presence(s).detach()
    base = model.g2.base(out["i_b"], otf, presence)
    assert float(presence[0]) == 0.0 and float(presence[1]) > 0.5
    assert torch.equal(out["restored"][0], base[0])
    with torch.no_grad():
        coarse_ungated, _ = model.g2(out["features"], base)
        coarse_base = downsample2(base)
        # the coarse estimate is base + p x correction exactly (the fine one sees the gated coarse estimate)
        torch.testing.assert_close(out["b"][0][1] - coarse_base[1], presence[1] * (coarse_ungated[1] - coarse_base[1]))
        assert float((coarse_ungated[1] - coarse_base[1]).abs().max()) > 1e-3
        assert float((out["restored"][1] - base[1]).abs().max()) > 1e-4
    with pytest.raises(Exception, match="model.g2_gate.*needs model.laser_gate=true"):
        ModelSpec(g2_residual=True, g2_gate=True)


def test_g2_base_is_checked():
    with pytest.raises(Exception, match="model.g2_base"):
        ModelSpec(g2_base="wiener")  # needs model.g2_residual=true
    with pytest.raises(Exception, match="model.g2_base"):
        ModelSpec(g2_residual=True, g2_base="sensor")

def test_laser_gate_passes_an_unlasered_image_and_moves_the_nsr_with_the_saturated_fraction():
    """model.laser_gate: presence p = f / (f + f0) of saturated pixels (f: their share of the field, padding not
    counted). An image without saturated pixels reaches G2 exactly as measured (G1's correction times p = 0) and is
    deconvolved at the unlasered nsr (padding filled, as always with g1_base=filled); a lasered one at
    log nsr = log nsr_0 + p (log nsr_1 - log nsr_0), per image."""
    model, s, otf, (clean, lasered) = _gated_pair(dict(g2_base_nsr=0.05, g2_base_nsr_lasered=50.0), "g1")
    out = model(s, otf)
    f = float(((lasered >= 0.999).sum() / (lasered > 0).sum()))
    assert f > 0.02
    torch.testing.assert_close(model.g2.laser_presence(s), torch.tensor([0.0, f / (f + 0.01)]))
    clean_filled = push_pull_fill(clean, valid_pixels(clean))  # only the padding filled
    assert torch.equal(out["i_b"][0], clean_filled[0])  # p = 0: G1 does nothing
    assert not torch.allclose(out["i_b"][1], push_pull_fill(lasered, valid_pixels(lasered))[0])
    p1 = f / (f + 0.01)
    nsr1 = float(torch.tensor(0.05).log() + p1 * (torch.tensor(50.0).log() - torch.tensor(0.05).log()))
    base = model.g2.base(out["i_b"], otf, model.g2.laser_presence(s))
    torch.testing.assert_close(base[0], _unit_dc_wiener(clean_filled, otf, 0.05)[0], atol=1e-6, rtol=0)
    torch.testing.assert_close(base[1], _unit_dc_wiener(out["i_b"][1:], otf, float(torch.tensor(nsr1).exp()))[0],
                               atol=1e-5, rtol=1e-5)
    out["restored"][1].square().mean().backward()
    for name in ("log_f0", "log_nsr_lasered"):
        assert float(getattr(model.g2, name).grad.abs()) > 0, name
    with pytest.raises(Exception, match="model.laser_gate"):
        ModelSpec(laser_gate=True, g1_residual=False)


def test_g1_runs_only_on_lasered_images_and_gives_the_whole_batchs_result():
    """An image without saturated pixels (p = 0) gets no G1 work: G1 sees only the lasered images of a batch, and
    the outputs and every gradient are those of G1 run on the whole batch in float64 (G1's layers are per image)."""
    model, s, otf, _ = _gated_pair({}, "g1")
    model = model.double()
    s, otf = s.double(), otf.to(torch.complex128)
    batch = torch.cat([s, s.flip(0), s[:1]])  # clean, lasered, lasered, clean, clean
    seen = []
    hook = model.g1.register_forward_hook(lambda m, i, o: seen.append(i[0].shape[0]))
    out = model(batch, otf)
    out["restored"].square().mean().backward()
    grads = [p.grad.clone() for p in model.parameters() if p.grad is not None]
    hook.remove()
    assert seen == [2]
    model.zero_grad()
    # the reference: the same chain with G1 run on every image (as on a GPU), its correction times p
    presence = model.g2.laser_presence(batch)
    assert presence.tolist()[0] == 0.0 and presence.tolist()[3:] == [0.0, 0.0] and min(presence[1:3]) > 0.5
    x = torch.cat([batch, coordinates(batch)], 1)
    i_b = push_pull_fill(batch, valid_pixels(batch)) + model.g1(x) * presence[:, None, None, None]
    torch.testing.assert_close(out["i_b"], i_b, rtol=1e-12, atol=1e-12)
    ref = model.g2(model.gv(i_b, otf), model.g2.base(i_b, otf, presence))
    ref[1].square().mean().backward()
    torch.testing.assert_close(out["restored"], ref[1], rtol=1e-12, atol=1e-12)
    ref_grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert len(grads) == len(ref_grads)
    for g, r in zip(grads, ref_grads):
        torch.testing.assert_close(g, r, rtol=1e-10, atol=1e-12)
    seen.clear()
    hook = model.g1.register_forward_hook(lambda m, i, o: seen.append(i[0].shape[0]))
    with torch.no_grad():
        clean = model(batch[[0, 3]], otf)
    hook.remove()
    assert seen == [] and torch.equal(clean["i_b"], push_pull_fill(batch[[0, 3]], valid_pixels(batch[[0, 3]])))


def test_a_non_square_image_is_filled_to_its_far_ends():
    """The pyramid halves until both sides reach one pixel: a wide image's short side gets there first, and the
    holes along its long side (here the last rows and columns) must still be filled."""
    for shape in ((136, 88), (17, 129), (1, 40), (40, 3)):
        x = torch.zeros(1, 1, *shape)
        x[..., shape[0] // 3: shape[0] // 2 + 1, shape[1] // 3: shape[1] // 2 + 1] = 0.4
        filled = push_pull_fill(x, valid_pixels(x))
        assert float((filled - 0.4).abs().max()) < 1e-6, shape
