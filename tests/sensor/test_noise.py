"""Noise terms of codesign.sensor.noise: statistics from large float64 samples, streams, straight-through rounding.

Tolerances are 4.5 standard errors of the estimator (computed from the sample itself), so each check is a
~1e-5 false-alarm test; seeds are fixed, so the outcome is deterministic.
"""
from __future__ import annotations

import math

import pytest
import torch

from codesign.sensor.noise import NoiseStreams, dark_current, photons, read_noise, round_ste
from . import _util as U

CPU = torch.device("cpu")
N_SIDE = 640  # 409,600 samples per statistic
Z = 4.5  # standard errors (benchmarks/bench_accuracy.py reports the largest |z| of the cases below next to it)


def _col(v: float) -> torch.Tensor:
    return torch.tensor(v, dtype=torch.float64).reshape(1, 1, 1, 1)


def _moments(x: torch.Tensor) -> tuple[float, float, float, float]:
    """(sample mean, sample variance, standard error of the mean, standard error of the variance)."""
    x = x.reshape(-1).to(torch.float64)
    n = x.numel()
    m = float(x.mean())
    d = x - m
    s2 = float((d**2).mean())
    m4 = float((d**4).mean())
    return m, s2, math.sqrt(max(s2, 1e-300) / n), math.sqrt(max(m4 - s2**2, 1e-300) / n)


def _z_scores(moments: tuple[float, float, float, float], mean: float, var: float) -> tuple[float, float]:
    """|z| of the sample mean and of the sample variance (``moments``: _moments of the sample) against ``mean`` and
    ``var``, in standard errors; a deviation within 1e-12 of the expected value (its rounding) counts as none."""
    m, s2, se_mean, se_var = moments
    return max(abs(m - mean) - 1e-12 * abs(mean), 0.0) / se_mean, max(abs(s2 - var) - 1e-12 * var, 0.0) / se_var


def mean_var_z(x: torch.Tensor, mean: float, var: float) -> float:
    """The larger |z| of the sample mean and the sample variance against ``mean`` and ``var`` (standard errors
    from the sample itself); NaN if either is NaN."""
    zs = _z_scores(_moments(x), mean, var)
    return math.nan if any(math.isnan(z) for z in zs) else max(zs)


def _check_mean_var(x: torch.Tensor, mean: float, var: float) -> None:
    """Sample mean and variance against the expected values within Z standard errors."""
    moments = _moments(x)
    m, s2, se_mean, se_var = moments
    z_mean, z_var = _z_scores(moments, mean, var)
    assert z_mean <= Z, f"mean {m} vs {mean} (se {se_mean})"
    assert z_var <= Z, f"variance {s2} vs {var} (se {se_var})"


# ---- photons --------------------------------------------------------------------------------------------------
PHOTON_CASES = [  # (mu, c1, c2, scale)
    (1e3, 0.0, 1.0, 1.0),     # pure shot noise: variance = mu
    (1e4, 0.2, 1.0, 1.0),     # shot + 20 % signal-proportional
    (50.0, 0.05, 0.9, 0.25),  # direct path of a 4x4 bin: std scaled by 1/4
    (2e5, 0.1, 1.1, 0.5),
    (3e3, 0.25, 0.0, 1.0),    # c2 = 0: only the proportional term
]


def photon_sample(mu: float, c1: float, c2: float, scale: float, side: int = N_SIDE):
    """(side x side photon draws at mean mu, their closed-form mean mu_p and variance (c2^2 mu + c1^2 mu^2) k^2)."""
    streams = NoiseStreams(11, CPU)
    m = torch.full((1, 1, side, side), mu, dtype=torch.float64)
    omega = photons(m, _col(c1), _col(c2), scale, streams)
    return omega, mu, (c2**2 * mu + c1**2 * mu**2) * scale**2


@pytest.mark.parametrize("mu,c1,c2,scale", PHOTON_CASES)
def test_photons_mean_and_variance(mu, c1, c2, scale):
    _check_mean_var(*photon_sample(mu, c1, c2, scale))


def test_photons_per_sample_coefficients_broadcast():
    """A batch mixing noise levels: each sample gets its own variance."""
    streams = NoiseStreams(3, CPU)
    mu = torch.full((2, 1, 400, 400), 2e3, dtype=torch.float64)
    c1 = torch.tensor([0.0, 0.1], dtype=torch.float64).reshape(2, 1, 1, 1)
    c2 = torch.tensor([1.0, 0.0], dtype=torch.float64).reshape(2, 1, 1, 1)
    omega = photons(mu, c1, c2, 1.0, streams)
    _check_mean_var(omega[0], 2e3, 2e3)
    _check_mean_var(omega[1], 2e3, (0.1 * 2e3) ** 2)


def test_photons_without_noise_is_the_mean_exactly():
    streams = NoiseStreams(0, CPU)
    mu = torch.rand(1, 1, 8, 8, dtype=torch.float64) * 1e4
    out = photons(mu, _col(0.0), _col(0.0), 1.0, streams)
    assert torch.equal(out, mu)


def test_photons_gradient_is_finite_at_black_pixels():
    """d sqrt(var) / d mu is infinite at mu = 0 without the clamp; the reparameterized draw must stay finite."""
    streams = NoiseStreams(0, CPU)
    mu = torch.tensor([0.0, 0.0, 1e-30, 5.0, 1e4], dtype=torch.float64).reshape(1, 1, 1, 5).requires_grad_(True)
    omega = photons(mu, _col(0.2), _col(1.0), 1.0, streams)
    (g,) = torch.autograd.grad(omega.sum(), mu)
    assert bool(torch.isfinite(omega).all()) and bool(torch.isfinite(g).all())
    # reparameterization: d omega / d mu = 1 + d sigma / d mu * eps, ~1 for a bright pixel
    assert abs(float(g[0, 0, 0, 4]) - 1.0) < 0.1


# ---- dark current ---------------------------------------------------------------------------------------------
DARK_CASES = [(0.002, 1.0), (0.002, 16.0), (3.0, 1.0), (3.0, 97.81), (0.5, 9.0)]  # (mu_c, n_eff)


def dark_sample(mu_c: float, n_eff: float, side: int = N_SIDE):
    """(side x side dark-current draws Poisson(n_eff mu_c) / n_eff, their closed-form mean mu_c and variance
    mu_c / n_eff)."""
    streams = NoiseStreams(5, CPU)
    like = torch.zeros(1, 1, side, side, dtype=torch.float64)
    return dark_current(_col(mu_c), like, n_eff, streams), mu_c, mu_c / n_eff


@pytest.mark.parametrize("mu_c,n_eff", DARK_CASES)
def test_dark_current_is_poisson_averaged(mu_c, n_eff):
    like = torch.zeros(1, 1, N_SIDE, N_SIDE, dtype=torch.float64)
    d, mean, var = dark_sample(mu_c, n_eff)
    assert d.shape == like.shape and d.dtype == like.dtype
    # Poisson(n_eff mu_c) / n_eff: non-negative multiples of 1 / n_eff
    k = d * n_eff
    assert bool((k >= 0).all())
    torch.testing.assert_close(k, torch.round(k), rtol=0, atol=1e-9)
    _check_mean_var(d, mean, var)


def test_dark_current_zero_is_skipped_and_float32_draws_match_float64():
    streams = NoiseStreams(5, CPU)
    like = torch.zeros(1, 1, 4, 4, dtype=torch.float64)
    assert dark_current(_col(0.0), like, 1.0, streams) is None
    d64 = dark_current(_col(2.0), like, 4.0, NoiseStreams(9, CPU))
    d32 = dark_current(_col(2.0).float(), like.float(), 4.0, NoiseStreams(9, CPU))
    assert d32.dtype == torch.float32
    assert torch.equal(d32, d64.float())


# ---- read noise -----------------------------------------------------------------------------------------------
READ_CASES = [(390.0, 10.5, 1.0), (350.0, 11.0, 0.25), (0.0, 3.0, 1 / 9.89)]  # (mu_r, sigma_r, scale)


def read_sample(mu_r: float, sigma_r: float, scale: float, side: int = N_SIDE):
    """(side x side read-noise draws, their closed-form mean mu_r and variance (sigma_r k)^2)."""
    streams = NoiseStreams(7, CPU)
    like = torch.zeros(1, 1, side, side, dtype=torch.float64)
    return read_noise(_col(mu_r), _col(sigma_r), like, scale, streams), mu_r, (sigma_r * scale) ** 2


@pytest.mark.parametrize("mu_r,sigma_r,scale", READ_CASES)
def test_read_noise_mean_and_std(mu_r, sigma_r, scale):
    r, mean, var = read_sample(mu_r, sigma_r, scale)
    assert r.shape == (1, 1, N_SIDE, N_SIDE)
    _check_mean_var(r, mean, var)


def test_read_noise_without_std_is_its_mean():
    streams = NoiseStreams(7, CPU)
    like = torch.zeros(2, 1, 5, 5, dtype=torch.float64)
    mean = torch.tensor([390.0, 350.0], dtype=torch.float64).reshape(2, 1, 1, 1)
    r = read_noise(mean, torch.zeros_like(mean), like, 1.0, streams)
    assert torch.equal(r.expand_as(like), mean.expand_as(like))
    # the reference (no-skip) evaluation gives the same values
    r2 = read_noise(mean, torch.zeros_like(mean), like, 1.0, NoiseStreams(7, CPU), skip=False)
    assert torch.equal(r2, mean.expand_as(like))


# ---- rounding -------------------------------------------------------------------------------------------------
def test_round_ste_forward_is_round_and_gradient_is_one():
    x = torch.tensor([-2.5, -1.49, -0.5, 0.0, 0.3, 0.5, 0.51, 1.5, 2.5, 9434.7], dtype=torch.float64,
                     requires_grad=True)
    y = round_ste(x)
    assert torch.equal(y.detach(), torch.round(x.detach()))
    w = torch.arange(1.0, 11.0, dtype=torch.float64)
    (g,) = torch.autograd.grad((y * w).sum(), x)
    assert torch.equal(g, w)


# ---- streams --------------------------------------------------------------------------------------------------
def _draws(streams: NoiseStreams, like: torch.Tensor):
    return (streams.normal("photon", like), streams.uniform("quant", like), streams.normal("read", like),
            streams.poisson("dark", torch.full_like(like, 3.0)))


def test_streams_same_seed_reproduces_and_other_seed_differs():
    like = torch.zeros(64, 64, dtype=torch.float64)
    a, b, c = _draws(NoiseStreams(42, CPU), like), _draws(NoiseStreams(42, CPU), like), _draws(NoiseStreams(43, CPU), like)
    for x, y, z in zip(a, b, c):
        assert torch.equal(x, y)
        assert not torch.equal(x, z)
    # the terms are different streams: photon and read normals of one seed are not the same numbers
    assert not torch.equal(a[0], a[2])
    # uniform draws lie in [-0.5, 0.5)
    assert float(a[1].min()) >= -0.5 and float(a[1].max()) < 0.5


def test_streams_float32_draws_are_float64_draws_cast():
    like64 = torch.zeros(32, 32, dtype=torch.float64)
    n64 = NoiseStreams(1, CPU).normal("read", like64)
    n32 = NoiseStreams(1, CPU).normal("read", like64.float())
    assert n32.dtype == torch.float32 and torch.equal(n32, n64.float())


def test_skipping_a_term_leaves_the_other_draws_bit_identical():
    like = torch.zeros(1, 1, 32, 32, dtype=torch.float64)
    mu = torch.full_like(like, 1e3)
    mean, std = _col(390.0), _col(10.5)

    s_skip = NoiseStreams(8, CPU)
    photons(mu, _col(0.0), _col(0.0), 1.0, s_skip)                 # photon term skipped (no draw)
    assert dark_current(_col(0.0), like, 1.0, s_skip) is None        # dark term skipped
    r_skip = read_noise(mean, std, like, 1.0, s_skip)

    s_all = NoiseStreams(8, CPU)
    photons(mu, _col(0.2), _col(1.0), 1.0, s_all)                   # photon term drawn
    dark_current(_col(1.0), like, 1.0, s_all)                        # dark term drawn
    r_all = read_noise(mean, std, like, 1.0, s_all)
    assert torch.equal(r_skip, r_all)


def test_quantization_draws_do_not_depend_on_other_terms_through_the_simulator():
    """Direct path: sensor_dn - G e is the quantization draw; it must not change when read noise is switched on."""
    sim = U.make_sim(U.ODD, 9, 9, path="direct")
    coded, _, _ = U.states(U.ODD)
    scene = U.random_scene(sim)
    quiet = sim(scene, U.params(alpha_b=0.5), coded, seed=4)
    # read noise mean only: e shifts by mu_r exactly, no draw from the read stream
    shifted = sim(scene, U.params(alpha_b=0.5, read_noise_mean_e=390.0), coded, seed=4)
    g = sim.sensor.gain_dn_per_e
    torch.testing.assert_close(shifted["sensor_dn"] - quiet["sensor_dn"],
                               torch.full_like(quiet["sensor_dn"], g * 390.0), rtol=0, atol=1e-9)
