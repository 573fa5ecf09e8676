"""Figures of merit (LSR, BSR, OTF/MTF, radial MTF) and the safe atan2."""
from __future__ import annotations

import math

import pytest
import torch

from codesign.optics import OpticalSystem, OpticsSpec, RadialMTF, bsr, lsr_sampled, lsr_smooth, mtf, otf
from codesign.optics.atan2 import atan_of_ratio
from codesign.optics.masks import published_halfring
from tests.tolerances import assert_within_ulps

PS = [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 256.0, 1024.0, 1e4]


@pytest.fixture(scope="module")
def system():
    return OpticalSystem(OpticsSpec.with_samples_across(64, focal_n=64), dtype=torch.float64)


@pytest.fixture(scope="module")
def psfs(system):
    g = system.grid
    rand = (torch.rand(g.n, g.n, dtype=torch.float64, generator=torch.Generator().manual_seed(11)) * 2 - 1) * 3
    return {
        "uncoded": system.uncoded_psf(),
        "halfring": system.psf(published_halfring(g, system.spec.aperture_diameter_m).phase().detach()),
        "random": system.psf(rand),
    }


# ---- LSR ------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["uncoded", "halfring", "random"])
def test_lsr_smooth_decreases_to_lsr_sampled(system, psfs, name):
    psf = psfs[name]
    h0 = system.uncoded_peak
    hard = float(lsr_sampled(psf, h0))
    assert hard == pytest.approx(float(psf.max()) / h0, rel=1e-15)
    vals = [float(lsr_smooth(psf, h0, p)) for p in PS]
    assert all(v >= hard * (1 - 1e-12) for v in vals)
    assert all(a >= b * (1 - 1e-12) for a, b in zip(vals, vals[1:])), vals
    assert vals[0] == pytest.approx(float(psf.sum()) / h0, rel=1e-12)  # p = 1: the window energy
    # p-norm vs max: max <= ||h||_p <= N^(1/p) max
    n = psf.numel()
    for p, v in zip(PS, vals):
        assert v <= hard * n ** (1 / p) * (1 + 1e-12)
    assert vals[-1] == pytest.approx(hard, rel=2e-3)


def test_lsr_smooth_float32_does_not_overflow(system, psfs):
    psf = psfs["halfring"].float()
    h0 = system.uncoded_peak
    v = lsr_smooth(psf, h0, p=1024.0)
    assert bool(torch.isfinite(v))
    assert float(v) == pytest.approx(float(lsr_smooth(psfs["halfring"], h0, p=1024.0)), rel=1e-4)
    assert float(v) >= float(lsr_sampled(psf, h0)) * (1 - 1e-6)


def test_lsr_batched(system, psfs):
    stack = torch.stack([psfs["uncoded"], psfs["halfring"]])
    h0 = system.uncoded_peak
    assert lsr_sampled(stack, h0).shape == (2,)
    assert lsr_smooth(stack, h0, 16.0).shape == (2,)
    assert float(lsr_sampled(stack, h0)[0]) == pytest.approx(1.0, abs=1e-9)
    torch.testing.assert_close(lsr_smooth(stack, h0, 16.0)[1], lsr_smooth(psfs["halfring"], h0, 16.0))


def test_lsr_smooth_gradient_is_that_of_the_p_norm(system, psfs):
    psf = psfs["halfring"].clone().requires_grad_(True)
    h0, p = system.uncoded_peak, 8.0
    (g,) = torch.autograd.grad(lsr_smooth(psf, h0, p), psf)
    h = psfs["halfring"]
    norm = h.pow(p).sum().pow(1 / p)
    expected = (h / norm).pow(p - 1) / h0
    torch.testing.assert_close(g, expected, rtol=1e-10, atol=1e-14)


# ---- BSR -------------------------------------------------------------------------------------------------------
def test_bsr_of_uncoded_with_itself_is_one(psfs):
    assert float(bsr(psfs["uncoded"], psfs["uncoded"])) == 1.0


def test_bsr_is_window_energy_ratio(psfs):
    b = float(bsr(psfs["halfring"], psfs["uncoded"]))
    assert b == pytest.approx(float(psfs["halfring"].sum() / psfs["uncoded"].sum()), rel=1e-15)
    assert 0 < b < 1  # the half ring throws light outside this small window


# ---- OTF / MTF -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["uncoded", "halfring", "random"])
def test_mtf_is_one_at_dc_and_at_most_one(psfs, name):
    m = mtf(psfs[name])
    assert float(m[0, 0]) == pytest.approx(1.0, abs=1e-12)
    assert float(m.max()) <= 1 + 1e-12
    assert float(m.min()) >= 0
    o = otf(psfs[name])
    assert float(o[0, 0].real) == pytest.approx(1.0, abs=1e-15) and float(o[0, 0].imag) == pytest.approx(0, abs=1e-15)
    # a real PSF has a Hermitian OTF: O(-k) = conj(O(k))
    flipped = torch.roll(torch.flip(o, dims=(0, 1)), shifts=(1, 1), dims=(0, 1))
    torch.testing.assert_close(flipped, o.conj(), rtol=1e-9, atol=1e-12)


def test_mtf_of_a_shifted_psf_is_unchanged(psfs):
    psf = psfs["uncoded"]
    torch.testing.assert_close(mtf(torch.roll(psf, shifts=(3, -5), dims=(0, 1))), mtf(psf), rtol=1e-9, atol=1e-12)


def test_mtf_of_a_delta_is_flat():
    d = torch.zeros(16, 16, dtype=torch.float64)
    d[8, 8] = 0.3
    torch.testing.assert_close(mtf(d), torch.ones(16, 16, dtype=torch.float64), rtol=0, atol=1e-12)


@pytest.mark.parametrize("m", [16, 33, 64])
def test_radial_mtf_of_ones_is_ones(m):
    spec = OpticsSpec.with_samples_across(64, focal_n=m)
    radial = RadialMTF(spec)
    out = radial(torch.ones(m, m, dtype=torch.float64))
    assert_within_ulps(out, torch.ones_like(out), 4)  # an average of ones: the rounding of the bin sums
    assert float(radial.counts.sum()) == m * m
    assert float(radial.counts[0]) == 1  # DC alone in bin 0
    assert float(radial.freqs[0]) == 0.0
    step = 1 / (m * spec.focal_pitch_m) / spec.cutoff_frequency
    torch.testing.assert_close(radial.freqs[1:] - radial.freqs[:-1], torch.full_like(radial.freqs[1:], step))
    # batched input
    assert radial(torch.ones(2, 3, m, m)).shape == (2, 3, radial.freqs.numel())


def test_radial_mtf_of_radial_function(system):
    spec = system.spec
    radial = RadialMTF(spec)
    m, dx = spec.focal_n, spec.focal_pitch_m
    f = torch.fft.fftfreq(m, d=dx, dtype=torch.float64)
    nu = torch.sqrt(f[:, None] ** 2 + f[None, :] ** 2) / spec.cutoff_frequency
    out = radial(torch.exp(-nu))
    step = float(radial.freqs[1])
    # each bin averages exp(-nu) over |nu - centre| <= step / 2
    assert float((out - torch.exp(-radial.freqs)).abs().max()) <= 0.6 * step


def test_radial_summary_band(system):
    radial = RadialMTF(system.spec)
    rad = radial.freqs.clone()
    band = (0.0, 0.5)
    sel = radial.band_mask(band)
    assert not bool(sel[0])  # DC excluded
    assert bool((radial.freqs[sel] <= 0.5).all()) and bool((radial.freqs[sel] > 0).all())
    mean, mn = radial.summary(rad, band)
    assert float(mean) == pytest.approx(float(radial.freqs[sel].mean()), rel=1e-15)
    assert float(mn) == pytest.approx(float(radial.freqs[sel].min()), rel=1e-15)


# ---- atan2 / atan of a ratio ----------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_torch_atan2_gradient_is_zero_at_origin(dtype):
    # The atan2 convention relies on torch.atan2 giving a finite (zero) gradient at a pupil-field zero.
    y = torch.zeros(3, dtype=dtype, requires_grad=True)
    x = torch.zeros(3, dtype=dtype, requires_grad=True)
    gy, gx = torch.autograd.grad(torch.atan2(y, x).sum(), (y, x))
    assert float(gy.abs().max()) == 0.0 and float(gx.abs().max()) == 0.0


def test_atan_of_ratio_gradcheck_and_finite_at_zero_denominator():
    gen = torch.Generator().manual_seed(1)
    y = torch.randn(6, dtype=torch.float64, generator=gen).requires_grad_(True)
    x = torch.randn(6, dtype=torch.float64, generator=gen).requires_grad_(True)
    assert torch.autograd.gradcheck(atan_of_ratio, (y, x))
    y0 = torch.tensor([1.0, -2.0, 0.0], dtype=torch.float64, requires_grad=True)
    x0 = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    gy, gx = torch.autograd.grad(atan_of_ratio(y0, x0).sum(), (y0, x0))
    assert bool(torch.isfinite(gy).all()) and bool(torch.isfinite(gx).all())
    # d/dx atan(y/x) = -y / (x^2 + y^2): at x = 0 it is -1/y
    torch.testing.assert_close(gx, torch.tensor([-1.0, 0.5, 0.0], dtype=torch.float64))


def test_atan_of_ratio_is_atan_of_ratio():
    gen = torch.Generator().manual_seed(2)
    y = torch.randn(500, dtype=torch.float64, generator=gen)
    x = torch.randn(500, dtype=torch.float64, generator=gen)
    out = atan_of_ratio(y, x)
    assert_within_ulps(out, torch.atan(y / x), 4, scale=math.pi / 2)  # two roundings of atan's range
    assert float(out.abs().max()) <= math.pi / 2
    edge = atan_of_ratio(torch.tensor([1.0, -1.0, 0.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    torch.testing.assert_close(edge, torch.tensor([math.pi / 2, -math.pi / 2, 0.0], dtype=torch.float64))
