"""Extreme scenes (all zero, all one, a single bright pixel) through the float32 sensor simulation, with and without
a laser, and through the restoration network.

The finiteness sweep over scene x alpha_b x exposure was moved here from tests/sensor/test_float32.py and extended
with the single-pixel scene and alpha_l = 1e8. The physics checks are what a black, a white and a point scene
allow exactly: the black level, the full-well value, and the point's spread into the PSF kernel with its energy.
The float64 versions of the noise-free checks live in tests/sensor (test_digitize, test_simulator, test_veil);
here they run in float32, with every quantization draw, and next to a saturating laser.
"""
from __future__ import annotations

import math

import pytest
import torch

from codesign.models import build_sgan, otf_from_kernel
from codesign.train.optim import init_weights
from tests.sensor import _util as U

F32 = torch.float32
N, R = 22, 66  # bin factor 3: the 11 px coarse kernel (13 px laser footprint) leaves most of the sensor
K = R // N
BLACK_E = 1000.0  # read-noise mean (black level) [e-]: G * 1000 = 370 DN exactly in float32 and float64
BLACK_DN = 370.0


def _finite(out: dict) -> None:
    for k, v in out.items():
        if v.is_floating_point():
            assert bool(torch.isfinite(v).all()), f"non-finite values in {k}"


def _scene(sim, kind: str, batch: int, dtype=F32) -> torch.Tensor:
    s = sim.scene_size
    if kind == "random":
        return U.random_scene(sim, batch=batch, dtype=dtype)
    if kind == "point":  # one bright pixel at the scene centre, everything else black
        x = torch.zeros(batch, 1, s, s, dtype=dtype)
        x[..., s // 2, s // 2] = 1.0
        return x
    return U.uniform_scene(sim, {"black": 0.0, "white": 1.0}[kind], batch=batch, dtype=dtype)


def _laser_box(sim, row: int, col: int) -> torch.Tensor:
    """(N, N) network pixels within the direct path's laser footprint centred on pixel (row, col)."""
    h = sim.footprint_size(sim.coarse) // 2
    m = torch.zeros(N, N, dtype=torch.bool)
    m[max(row - h, 0): row + h + 1, max(col - h, 0): col + h + 1] = True
    return m


def _axis_footprint(sim) -> torch.Tensor:
    """Pixels an on-axis laser can touch in either path: its centre (10.5, 10.5) rounds to pixel 10, a 13 px box
    (rows 4-16) in the direct path and sensor pixels 15-49 (network rows 5-16) in the full path."""
    return _laser_box(sim, N // 2 - 1, N // 2 - 1) | _laser_box(sim, N // 2 + 1, N // 2 + 1)


# ---- finiteness and range (moved from tests/sensor/test_float32.py) -------------------------------------------
@pytest.mark.parametrize("path", ["direct", "full"])
@pytest.mark.parametrize("alpha_b", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("scene_kind", ["black", "white", "point", "random"])
@pytest.mark.parametrize("exposure", [1e-4, 0.1, 1.0])
def test_float32_outputs_are_finite_and_in_range(path, alpha_b, scene_kind, exposure):
    sim = U.make_sim(U.ODD, 33, 11, path=path)
    coded, _, _ = U.states(U.ODD, F32)
    scene = _scene(sim, scene_kind, 3)
    p = U.params(3, dtype=F32, alpha_b=alpha_b, exposure_s=exposure, **U.NOISY).replace(
        alpha_l=torch.tensor([0.0, 1e6, 1e8]))
    out = sim(scene, p, coded, seed=0)
    _finite(out)
    s = sim.sensor
    assert float(out["sensor_dn"].min()) >= 0 and float(out["sensor_dn"].max()) <= s.saturation_dn
    # the network input is the counts over G e_sat, zero padded: in [0, s_sat / (G e_sat)]
    assert float(out["sensor"].min()) >= 0 and float(out["sensor"].max()) <= s.saturation_dn / U.full_well_dn(sim)
    assert float(out["laser"].min()) >= 0 and float(out["laser"][0].abs().max()) == 0.0
    assert bool(out["saturated"][2].any())  # alpha_l = 1e8 on the axis always saturates its core


# ---- a black scene reads the black level ----------------------------------------------------------------------
@pytest.mark.parametrize("laser", ["off", "outside", "centre_1e8"])
def test_black_scene_reads_the_black_level_exactly(laser):
    """All-zero scene, every noise term off except the read-noise mean mu_r (the black level): e = mu_r in every
    pixel, G mu_r = 370 counts, an integer, which dithered rounding leaves unchanged. The full path reads exactly
    370 everywhere (away from the laser's footprint), the direct path 370 plus its Gaussian quantization noise."""
    angle = {"off": 0.0, "outside": None, "centre_1e8": 0.0}[laser]
    alpha = {"off": 0.0, "outside": 1e8, "centre_1e8": 1e8}[laser]
    for path in ("full", "direct"):
        sim = U.make_sim(U.ODD, R, N, path=path, background_veil=True)
        coded, _, _ = U.states(U.ODD, F32)
        if angle is None:
            angle = U.laser_angle(sim, 40.0, -30.0)  # footprint entirely off the sensor
        p = U.params(2, dtype=F32, alpha_b=0.8, alpha_l=alpha, laser_angle_rad=angle, read_noise_mean_e=BLACK_E)
        out = sim(_scene(sim, "black", 2), p, coded, seed=5)
        _finite(out)
        assert float(sim.sensor.gain_dn_per_e * torch.tensor(BLACK_E, dtype=F32)) == BLACK_DN
        dn = out["sensor_dn"][:, 0].double()
        away = ~_axis_footprint(sim) if laser == "centre_1e8" else torch.ones(N, N, dtype=torch.bool)
        if laser == "centre_1e8":
            assert bool(out["saturated"].any())
        else:
            assert not bool(out["saturated"].any()) and float(out["laser"].abs().max()) == 0.0
        if path == "full":
            assert torch.equal(dn[:, away], torch.full_like(dn[:, away], BLACK_DN))
        else:
            noise = dn[:, away] - BLACK_DN
            sq = U.quant_std(sim)
            assert float(noise.abs().max()) < 5 * sq
            assert abs(float(noise.mean())) < 4.5 * sq / math.sqrt(noise.numel())
            assert abs(float(noise.std()) / sq - 1) < 0.1  # the quantization noise of a 3 x 3 average


# ---- a white scene reads alpha_b of full well -----------------------------------------------------------------
@pytest.mark.parametrize("path", ["direct", "full"])
@pytest.mark.parametrize("alpha_b", [0.5, 1.0, 2.0])
@pytest.mark.parametrize("alpha_l", [0.0, 1e8])
def test_white_scene_reads_alpha_b_of_full_well(path, alpha_b, alpha_l):
    """All-one scene through the coded mask with the out-of-window veil (the default): r_b = alpha_b exactly (BSR 1),
    so the counts are alpha_b G e_sat. alpha_b = 1 puts every pixel exactly on the saturation threshold (a float32
    tie: either side is right, but the counts must read full well within the quantization noise); alpha_b = 2
    saturates everything, and a laser on top cannot push a pixel beyond full well."""
    sim = U.make_sim(U.ODD, R, N, path=path, background_veil=True)
    coded, _, _ = U.states(U.ODD, F32)
    p = U.params(2, dtype=F32, alpha_b=alpha_b, alpha_l=alpha_l)
    out = sim(_scene(sim, "white", 2), p, coded, seed=2)
    _finite(out)
    fw, sq = U.full_well_dn(sim), U.quant_std(sim)
    dn, sat = out["sensor_dn"][:, 0].double(), out["saturated"][:, 0]
    away = ~_axis_footprint(sim) if alpha_l else torch.ones(N, N, dtype=torch.bool)
    x = alpha_b * fw
    if alpha_b < 1:
        assert not bool(sat[:, away].any())
        v = dn[:, away]
        if path == "full":  # dithered rounding of 4717.5: each sensor pixel reads 4717 or 4718, unbiased
            assert float((v - x).abs().max()) <= 0.5
            assert abs(float(v.mean()) - x) < 4.5 * 0.5 / K / math.sqrt(v.numel())
        else:
            assert float((v - x).abs().max()) < 5 * sq
            assert abs(float(v.mean()) - x) < 4.5 * sq / math.sqrt(v.numel())
    elif alpha_b == 1:
        assert float((dn - fw).abs().max()) < 1.0 + 5 * sq
        if path == "direct":
            assert torch.equal(sat, dn == fw)
    else:
        assert bool(sat.all()) and torch.equal(dn, torch.full_like(dn, fw))
    if alpha_l:  # the laser's core saturates whatever the background
        assert bool(sat[:, ~away].any())
    assert float(dn.max()) <= fw


# ---- a single bright pixel spreads into the PSF kernel with its energy -----------------------------------------
@pytest.mark.parametrize("alpha_l", [0.0, 1e8])
def test_point_scene_spreads_into_the_kernel_with_its_energy(alpha_l):
    """Direct path, float32, veil off: one scene pixel of radiance 1 at alpha_b becomes r_b = alpha_b k / E0 (the
    pixel-integrated PSF kernel k over the uncoded window energy E0), so the counts above the black level are
    G e_sat alpha_b k / E0 pixel by pixel and sum to G e_sat alpha_b sum(k) / E0: the energy the window PSF holds.
    A black level keeps the quantization noise away from the zero clamp (which would bias the sum). At alpha_b =
    300 the core saturates: exactly the pixels whose expected counts reach full well, and the clipped sum is the
    expected counts clipped at full well. A laser in the far corner must not change any of it."""
    sim = U.make_sim(U.ODD, R, N, path="direct")
    coded, _, _ = U.states(U.ODD, F32)
    alphas = [1.0, 300.0]
    angle = U.laser_angle(sim, -4.0, N + 3.0)  # footprint rows <= 2, cols >= 19: clear of the point's kernel
    p = U.params(2, dtype=F32, alpha_l=alpha_l, laser_angle_rad=angle, read_noise_mean_e=BLACK_E).replace(
        alpha_b=torch.tensor(alphas, dtype=F32))
    out = sim(_scene(sim, "point", 2), p, coded, seed=3)
    _finite(out)
    k = sim.kernel(coded).double() / coded.uncoded_energy
    ks, s = sim.coarse.ksize, sim.scene_size
    c = s // 2 - ks // 2  # the output pixel that sees the point (output i sees scene pixel i + ks // 2)
    spread = torch.zeros(N, N, dtype=torch.float64)
    spread[c - ks // 2: c + ks // 2 + 1, c - ks // 2: c + ks // 2 + 1] = k
    fw, sq = U.full_well_dn(sim), U.quant_std(sim)
    clear = ~_laser_box(sim, -4, N + 3)
    assert bool((spread > 0)[~clear].sum() == 0)
    for i, a in enumerate(alphas):
        dn, sat = out["sensor_dn"][i, 0].double(), out["saturated"][i, 0]
        expect = BLACK_DN + fw * a * spread  # counts without noise and without the full-well clip
        tie = (expect - fw).abs() <= 1e-4 * fw
        assert torch.equal(sat[clear & ~tie], (expect >= fw)[clear & ~tie])
        clipped = expect.clamp(max=fw)
        assert float((dn - clipped)[clear].abs().max()) < 5 * sq + 1e-4 * float(expect.max())
        # energy: sum of (counts - black level) over the point's spread; the sum's noise std is sq * sqrt(121)
        got = float((dn - BLACK_DN)[clear].sum())
        want = float((clipped - BLACK_DN)[clear].sum())
        assert abs(got - want) < 5 * sq * math.sqrt(int(clear.sum())) + 1e-5 * want
        if a == 1.0:  # nothing clips: the window's energy arrives in full
            assert not bool(sat[clear].any())
            assert abs(want - fw * a * float(k.sum())) < 1e-9 * want
        else:
            assert 0 < int(sat[clear].sum()) < 20 and got < fw * a * float(k.sum())
    if alpha_l:
        assert bool(out["saturated"][:, 0][:, ~clear].any())  # the laser does land, in its corner


def test_point_scene_full_path_energy_is_bounded_by_the_clamped_bicubic_lobes():
    """The full path resamples the network-resolution scene onto the sensor grid (bicubic, then clamped to [0, 1]):
    a single bright pixel's bicubic interpolant has negative lobes, and the clamp removes them, so its energy can
    only grow, at most by the factor of the clamped 2-D Keys kernel (a = -0.75) at 3 samples per pixel:
    (P^2 + M^2) / (P + M)^2 = 1.2469 with P = 10/3, M = -1/3 the 1-D positive and negative weight sums. Measured:
    1.245 (see the report of the stress tests; the direct path conserves it exactly)."""
    sim = U.make_sim(U.ODD, R, N, path="full")
    coded, _, _ = U.states(U.ODD, F32)
    out = sim(_scene(sim, "point", 1), U.params(1, dtype=F32, alpha_b=1.0, read_noise_mean_e=BLACK_E), coded,
              seed=3)
    _finite(out)
    conserved = U.full_well_dn(sim) * float(sim.kernel(coded).double().sum()) / coded.uncoded_energy
    got = float((out["sensor_dn"].double() - BLACK_DN).sum())
    p_sum, m_sum = 10.0 / 3.0, -1.0 / 3.0
    bound = (p_sum**2 + m_sum**2) / (p_sum + m_sum) ** 2
    assert bound == pytest.approx(1.2469, abs=1e-4)
    # the sum's noise: dithered rounding, std 1/sqrt(12) per sensor pixel, over K^2 per network pixel
    noise = 5 * math.sqrt(R * R / 12.0) / (K * K)
    assert conserved - noise <= got <= bound * conserved + noise


# ---- the restoration network ---------------------------------------------------------------------------------
@pytest.mark.parametrize("variant", ["sgan_b", "sgan_f"])
def test_restoration_network_is_finite_on_extreme_sensor_images(variant):
    """A tiny SGAN (eval mode, random weights) on the sensor images of extreme scenes (black, white saturated, a
    saturating point, a random scene under a 1e8 laser) and on synthetic extremes (all zero, all at full well, all
    at the ADC's full scale): every output finite, a sample's output independent of the rest of its batch (no
    batch statistics in eval mode), and the generator gradients finite (training on saturated inputs)."""
    padded = 48  # the tiny model's smallest input; holds the 22 px field plus the 11 px kernel
    sim = U.make_sim(U.ODD, R, N, padded_size=padded, background_veil=True)
    coded, _, _ = U.states(U.ODD, F32)
    kinds = ["black", "white", "point", "random"]
    scenes = torch.cat([_scene(sim, kind, 1) for kind in kinds])
    p = U.params(4, dtype=F32, **U.NOISY).replace(alpha_b=torch.tensor([0.5, 2.0, 300.0, 0.7]),
                                                  alpha_l=torch.tensor([0.0, 1e8, 0.0, 1e8]))
    sensor = sim(scenes, p, coded, seed=0)["sensor"]
    full_scale = sim.sensor.saturation_dn / U.full_well_dn(sim)
    synth = torch.stack([torch.full((1, padded, padded), v) for v in (0.0, 1.0, full_scale)])
    x = torch.cat([sensor, synth])
    otf = otf_from_kernel(sim.kernel(coded), padded)
    torch.manual_seed(0)
    model = build_sgan({"variant": variant, "size": "tiny"})
    init_weights(model)
    with torch.no_grad():  # the init leaves output layers at zero (outputs all 0): perturb every weight
        for q in model.parameters():
            q.add_(0.1 * torch.randn_like(q))
    model.eval()
    with torch.no_grad():
        out = model(x, otf)
        alone = [model(x[i:i + 1], otf)["b"][1] for i in range(len(x))]
    for name in ("i_b", "features"):
        assert bool(torch.isfinite(out[name]).all()), name
    for b in out["b"]:
        assert bool(torch.isfinite(b).all())
    fine = out["b"][1]
    scale = float(fine.abs().max())
    assert scale > 1e-3  # a live network, not the zero-initialized one
    for i in range(len(x)):
        # different batch sizes take different float32 convolution paths: round-off only (measured 4e-5 x scale)
        assert float((alone[i] - fine[i:i + 1]).abs().max()) <= 1e-3 * scale
    out = model(x, otf)
    loss = out["b"][1].square().mean() + out["b"][0].abs().mean() + out["i_b"].square().mean()
    params = [q for g in model.generators() for q in g.parameters()]
    grads = torch.autograd.grad(loss, params)
    assert all(bool(torch.isfinite(g).all()) for g in grads)
    assert sum(float(g.abs().sum()) for g in grads) > 0
