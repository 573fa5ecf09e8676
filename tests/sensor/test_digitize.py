"""Digitization: quantization noise, full-well saturation, the saturated mask and the ADC clip.

Geometry: the 33-sample optics window with bin factor 1 (resolution == image_size); the PSF kernel then spans
exactly one window period, so a uniform scene gives r_b = alpha_b sum(h) / sum(h0) exactly (alpha_b for the
uncoded PSF, alpha_b BSR for a coded one).
"""
from __future__ import annotations

import math

import pytest
import torch

from codesign.optics.metrics import bsr
from . import _util as U

PATHS = ["direct", "full"]


def _g_e(sim, r: torch.Tensor) -> torch.Tensor:
    """Noise-free G e for a relative irradiance r (no read mean), clamped at full well."""
    s = sim.sensor
    return s.gain_dn_per_e * (r * s.full_well_e).clamp(0, s.full_well_e)


# ---- quantization ---------------------------------------------------------------------------------------------
def test_full_path_quantization_is_dithered_rounding():
    """Full path, bin factor 1, every other noise term off: integer counts, error mean 0 and variance 1/6.

    Rounding x + U(-0.5, 0.5) to the nearest integer has error mean 0 for every x and variance f (1 - f) for
    fractional part f: 1/6 averaged over inputs. |error| < 1 always.
    """
    coded, _, _ = U.states(U.ODD)
    sim = U.make_sim(U.ODD, 24, 24, path="full")
    b = 32
    out = sim(U.random_scene(sim, batch=b), U.params(b, alpha_b=0.9), coded, seed=1)
    dn = out["sensor_dn"]
    assert torch.equal(dn, torch.round(dn))
    err = (dn - _g_e(sim, out["irradiance"])).reshape(-1)
    assert float(err.abs().max()) < 1.0
    n = err.numel()
    se_mean = math.sqrt(1 / 6 / n)
    assert abs(float(err.mean())) < 4.5 * se_mean
    se_var = math.sqrt(float((err**4).mean()) - (1 / 6) ** 2) / math.sqrt(n)
    assert abs(float((err**2).mean()) - 1 / 6) < 4.5 * se_var


DIRECT_QUANTIZATION_GEOMETRIES = [(9, 9), (33, 11)]  # (resolution, image_size): bin factors 1 and 3
QUANTIZATION_Z = 4.5  # standard errors of the mean and of the mean square


def direct_quantization_z(resolution: int, image_size: int) -> float:
    """Direct path, every other noise term off: the larger |z| of the mean and the mean square of
    sensor_dn - G e against N(0, w2 / 6), w2 = 1 / bin_factor^2 (standard errors of the Gaussian)."""
    coded, _, _ = U.states(U.ODD)
    sim = U.make_sim(U.ODD, resolution, image_size, path="direct")
    b = 256
    out = sim(U.random_scene(sim, batch=b), U.params(b, alpha_b=0.9), coded, seed=2)
    err = (out["sensor_dn"] - _g_e(sim, out["irradiance"])).reshape(-1)
    var = 1.0 / sim.sensor.bin_factor**2 / 6
    n = err.numel()
    return max(abs(float(err.mean())) / math.sqrt(var / n),
               abs(float((err**2).mean()) - var) / (var * math.sqrt(2 / n)))


@pytest.mark.parametrize("resolution,image_size", DIRECT_QUANTIZATION_GEOMETRIES)
def test_direct_path_quantization_is_gaussian_of_the_binned_rounding_variance(resolution, image_size):
    """Direct path: sensor_dn - G e ~ N(0, w2 / 6), w2 = 1 / bin_factor^2."""
    assert direct_quantization_z(resolution, image_size) < QUANTIZATION_Z


# ---- full well ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("path", PATHS)
def test_uniform_scene_at_alpha_b_one_sits_at_full_well(path):
    """Uncoded PSF, uniform white scene, alpha_b = 1, all noise off: e = e_sat -> round(G e_sat) counts."""
    _, uncoded, _ = U.states(U.ODD)
    sim = U.make_sim(U.ODD, 9, 9, path=path)
    out = sim(U.uniform_scene(sim), U.params(alpha_b=1.0), uncoded, seed=0)
    torch.testing.assert_close(out["irradiance"], torch.ones_like(out["irradiance"]), rtol=0, atol=1e-12)
    target = U.full_well_dn(sim)  # 0.37 * 25500 = 9435
    assert target == 9435.0
    if path == "full":  # an integer input is left unchanged by dithered rounding
        assert torch.equal(out["sensor_dn"], torch.full_like(out["sensor_dn"], target))
    else:  # plus the Gaussian quantization noise of the direct path
        assert float((out["sensor_dn"] - target).abs().max()) < 5 * U.quant_std(sim)
    torch.testing.assert_close(out["sensor"], out["sensor_dn"] / target, rtol=1e-15, atol=0)


@pytest.mark.parametrize("path", PATHS)
def test_brighter_than_full_well_is_clipped_and_flagged(path):
    _, uncoded, _ = U.states(U.ODD)
    sim = U.make_sim(U.ODD, 9, 9, path=path)
    scene = U.uniform_scene(sim)
    a = sim(scene, U.params(alpha_b=1.01), uncoded, seed=3)
    b = sim(scene, U.params(alpha_b=50.0), uncoded, seed=3)
    assert bool(a["saturated"].all()) and bool(b["saturated"].all())
    # e is clamped to exactly e_sat in both, so with the same seed the counts are bit-identical
    assert torch.equal(a["sensor_dn"], b["sensor_dn"])
    if path == "full":
        assert torch.equal(a["sensor_dn"], torch.full_like(a["sensor_dn"], U.full_well_dn(sim)))


@pytest.mark.parametrize("path", PATHS)
def test_just_below_full_well_stays_linear(path):
    """alpha_b = 0.99: not saturated, counts = G 0.99 e_sat up to the quantization (9340.65 -> 9340 or 9341)."""
    _, uncoded, _ = U.states(U.ODD)
    sim = U.make_sim(U.ODD, 9, 9, path=path)
    out = sim(U.uniform_scene(sim, batch=4), U.params(4, alpha_b=0.99), uncoded, seed=5)
    x = sim.sensor.gain_dn_per_e * 0.99 * sim.sensor.full_well_e
    dn = out["sensor_dn"]
    assert not bool(out["saturated"].any())
    if path == "full":
        assert bool(((dn == math.floor(x)) | (dn == math.ceil(x))).all())
        # dithering is unbiased: the mean of 324 pixels is x within 4.5 standard errors
        f = x - math.floor(x)
        assert abs(float(dn.mean()) - x) < 4.5 * math.sqrt(f * (1 - f) / dn.numel())
    else:
        assert float((dn - x).abs().max()) < 5 * U.quant_std(sim)
    assert float(dn.max()) < U.full_well_dn(sim) - 90  # 1 % below full well is ~94 counts


@pytest.mark.parametrize("path", PATHS)
def test_coded_uniform_scene_saturates_at_alpha_b_one_over_bsr(path):
    """Coded PSF: r_b = alpha_b BSR, so the sensor saturates at alpha_b = 1 / BSR, not at 1."""
    coded, _, h0 = U.states(U.ODD)
    k = float(bsr(coded.psf, h0))
    assert 0.05 < k < 0.2
    sim = U.make_sim(U.ODD, 9, 9, path=path)
    scene = U.uniform_scene(sim)
    above = sim(scene, U.params(alpha_b=1.01 / k), coded, seed=0)
    below = sim(scene, U.params(alpha_b=0.99 / k), coded, seed=0)
    assert bool(above["saturated"].all()) and not bool(below["saturated"].any())
    x = sim.sensor.gain_dn_per_e * 0.99 * sim.sensor.full_well_e
    tol = 1.0 if path == "full" else 5 * U.quant_std(sim)
    assert float((below["sensor_dn"] - x).abs().max()) < tol


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("read_mean", [0.0, 390.0])
def test_saturated_mask_is_exactly_e_at_or_above_full_well(path, read_mean):
    """A ramp scene crossing full well: saturated == (r e_sat + mu_r >= e_sat); clipped pixels read G e_sat."""
    _, uncoded, _ = U.states(U.ODD)
    sim = U.make_sim(U.ODD, 24, 24, path=path)
    s = sim.scene_size
    ramp = torch.linspace(0, 1, s, dtype=torch.float64)
    scene = (ramp[None, :] * 0.7 + ramp[:, None] * 0.3).expand(1, 1, s, s).contiguous()
    out = sim(scene, U.params(alpha_b=1.7, read_noise_mean_e=read_mean), uncoded, seed=0)
    e_sat = sim.sensor.full_well_e
    e = out["irradiance"] * e_sat + read_mean
    clear = (e - e_sat).abs() > 1e-6 * e_sat  # exclude pixels within rounding distance of the threshold
    assert int(clear.sum()) > 500
    expect = e >= e_sat
    assert 50 < int(expect.sum()) < 500  # the ramp crosses full well inside the sensor
    assert torch.equal(out["saturated"][clear], expect[clear])
    dn = out["sensor_dn"]
    g = sim.sensor.gain_dn_per_e
    if path == "full":
        assert torch.equal(dn[expect & clear], torch.full_like(dn[expect & clear], U.full_well_dn(sim)))
        assert float((dn[~expect] - g * e[~expect]).abs().max()) < 1.0
    else:
        tol = 5 * U.quant_std(sim)
        assert float((dn[expect & clear] - U.full_well_dn(sim)).abs().max()) < tol
        assert float((dn[~expect] - g * e[~expect]).abs().max()) < tol


def test_counts_are_clipped_at_the_adc_range():
    """bit_depth 12: s_sat = 4095 < G e_sat, so bright pixels clip at 4095 counts before full well."""
    _, uncoded, _ = U.states(U.ODD)
    sim = U.make_sim(U.ODD, 9, 9, path="full", bit_depth=12)
    assert sim.sensor.saturation_dn == 4095.0
    out = sim(U.uniform_scene(sim), U.params(alpha_b=0.8), uncoded, seed=0)  # G e = 7548 counts
    assert torch.equal(out["sensor_dn"], torch.full_like(out["sensor_dn"], 4095.0))
    assert not bool(out["saturated"].any())  # the well is not full, only the ADC range is exceeded


@pytest.mark.parametrize("path", PATHS)
def test_black_scene_reads_the_read_noise_mean(path):
    _, uncoded, _ = U.states(U.ODD)
    sim = U.make_sim(U.ODD, 9, 9, path=path)
    out = sim(U.uniform_scene(sim, 0.0), U.params(alpha_b=0.7, read_noise_mean_e=390.0), uncoded, seed=0)
    g = sim.sensor.gain_dn_per_e
    tol = 1.0 if path == "full" else 5 * U.quant_std(sim)
    assert float((out["sensor_dn"] - g * 390.0).abs().max()) < tol
    assert bool((out["sensor_dn"] >= 0).all())


@pytest.mark.parametrize("downsample", ["area", "bicubic_aa"])
def test_full_path_downsampled_counts_stay_physical(downsample):
    """Full path: sensor counts are clamped to [0, s_sat] at sensor resolution and the laser irradiance is >= 0;
    binning them to the network resolution must keep them in [0, G e_sat] (the largest count a pixel can hold)
    and keep r_l >= 0. A black scene with a saturating laser (sharp saturated core next to dark pixels)."""
    coded, _, _ = U.states(U.ODD)
    sim = U.make_sim(U.ODD, 66, 22, path="full", downsample=downsample)
    out = sim(U.uniform_scene(sim, 0.0), U.params(alpha_b=0.5, alpha_l=1e6), coded, seed=0)
    dn, laser = out["sensor_dn"], out["laser"]
    assert bool(out["saturated"].any())
    assert float(dn.min()) >= 0.0, f"negative counts: min {float(dn.min()):.1f}"
    assert float(dn.max()) <= U.full_well_dn(sim), f"counts above full well: max {float(dn.max()):.1f}"
    assert float(laser.min()) >= 0.0, f"negative laser irradiance: min {float(laser.min()):.3g}"
