"""Wiener deconvolution (codesign/models/wiener.py) at its limits: OTF zeros, zero-power inputs, gamma -> 0 and huge.

The filter is  out = F^-1{ Y conj(H) P / (|H|^2 P + gamma) }  (learnable: P = mean(f^2) per image and feature;
classical: P = 1, gamma = nsr). Its closed-form limits, asserted here:
  * OTF = 1, gamma -> 0:     out = y P / (P + gamma) -> y                    (identity)
  * gamma huge:              out = (P / gamma) F^-1{ Y conj(H) } (1 + O(|H|^2 P / gamma)) -> 0
  * constant image c, H(0) = 1: only DC is present: out = c c^2 / (c^2 + gamma) everywhere
  * OTF zero except DC:      out = mean(y) H(0) P / (|H(0)|^2 P + gamma), a constant image
  * all-zero input:          out = 0, and so are the gradients (P = 0 and Y = 0)
  * gamma = 0 with exact OTF zeros: the pseudo-inverse, nothing where H = 0, the rest inverted
The float64 suite checks the regular regime (tests/models/test_wiener.py); this one the edges, in both precisions.
"""
from __future__ import annotations

import re

import pytest
import torch

from codesign.models import classical_wiener, otf_from_kernel, wiener_filter
from codesign.models.wiener import LearnableWiener

N = 18  # a 3 x 3 box's OTF, (1 + 2 cos(2 pi k / 18)) / 3 per axis, vanishes at k = 6 and 12
C = 3
GAMMAS = [0.0, 1e-30, 1e-12, 1e12, 1e30]
OTFS = ["box", "box_exact", "dc_only", "identity"]


def _box() -> torch.Tensor:
    k = torch.zeros(5, 5, dtype=torch.float64)
    k[1:4, 1:4] = 1.0 / 9.0
    return k


def _otf(kind: str, dtype) -> torch.Tensor:
    """The OTF on the N x N grid (rfft layout), complex64 for float32 and complex128 for float64."""
    cdtype = torch.complex64 if dtype == torch.float32 else torch.complex128
    if kind in ("box", "box_exact"):
        h = otf_from_kernel(_box(), N)  # "box": the zeros as computed, |H| ~ 1e-17 (FFT round-off)
        if kind == "box_exact":
            h = torch.where(h.abs() < 1e-12, torch.zeros_like(h), h)
    elif kind == "dc_only":
        h = torch.zeros(N, N // 2 + 1, dtype=torch.complex128)
        h[0, 0] = 1.0
    else:
        h = torch.ones(N, N // 2 + 1, dtype=torch.complex128)
    return h.to(cdtype)


def _inputs(dtype) -> torch.Tensor:
    """(3, C, N, N): a random image, an all-zero one (zero feature power), a constant one (DC only)."""
    g = torch.Generator().manual_seed(0)
    rand = torch.rand(C, N, N, generator=g, dtype=torch.float64)
    return torch.stack([rand, torch.zeros_like(rand), torch.full_like(rand, 0.7)]).to(dtype)


def _learnable(gamma: float, dtype) -> LearnableWiener:
    if gamma == 0.0:  # gamma_min = 0 and rho -> -inf: softplus underflows to exactly 0
        lw = LearnableWiener(C, gamma_init=1.0, gamma_min=0.0)
        with torch.no_grad():
            lw.rho.fill_(-1e4)
    else:
        lw = LearnableWiener(C, gamma_init=gamma, gamma_min=0.0)
    lw = lw.to(dtype)
    if gamma == 0.0:
        assert torch.equal(lw.gamma, torch.zeros(C, dtype=dtype))
    else:
        torch.testing.assert_close(lw.gamma.double(), torch.full((C,), gamma, dtype=torch.float64), rtol=1e-6,
                                   atol=0)
    return lw


def _gamma(lw: LearnableWiener) -> torch.Tensor:
    """The module's gamma as a (1, C, 1, 1) float64 tensor: rho is stored in float32 at construction, so gamma is
    the nominal value to float32 rounding (1e12 -> 999999995904); closed forms use the value the filter uses."""
    return lw.gamma.detach().double().view(1, C, 1, 1)


def _power(f: torch.Tensor) -> torch.Tensor:
    return f.double().square().mean(dim=(-2, -1), keepdim=True)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("gamma", GAMMAS)
@pytest.mark.parametrize("otf_kind", OTFS)
def test_learnable_wiener_outputs_and_gradients_are_finite(dtype, gamma, otf_kind):
    lw = _learnable(gamma, dtype)
    f = _inputs(dtype).requires_grad_(True)
    otf = _otf(otf_kind, dtype)
    out = lw(f, otf)
    assert out.dtype == dtype and bool(torch.isfinite(out).all())
    w = torch.randn(out.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64).to(dtype)
    gf, grho = torch.autograd.grad((out * w).sum() + out.square().mean(), (f, lw.rho))
    # the all-zero image: out = 0 exactly, and no gradient flows through it (Y = 0 and P = 0 both vanish)
    assert torch.count_nonzero(out[1]) == 0 and torch.count_nonzero(gf[1]) == 0
    if dtype == torch.float32 and gamma < 1e-12 and otf_kind == "box":
        # |H| ~ 1e-17 where the box's OTF vanishes: with gamma < 1e-12 the filter is the inverse 1 / H ~ 1e17 there
        # and d out / d gamma ~ Y H P / (|H|^2 P + gamma)^2 ~ 1e43, beyond float32's range. That is the true
        # derivative overflowing, not a defect: the module's default gamma_min = 1e-8 keeps float32 away from it.
        return
    assert bool(torch.isfinite(gf).all()) and bool(torch.isfinite(grho).all())


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-5), (torch.float64, 1e-12)])
@pytest.mark.parametrize("gamma", [0.0, 1e-30, 1e-12])
def test_identity_otf_and_vanishing_gamma_is_the_identity(dtype, tol, gamma):
    f = _inputs(dtype)
    lw = _learnable(gamma, dtype)
    out = lw(f, _otf("identity", dtype)).detach()
    p = _power(f)
    expect = f.double() * torch.where(p > 0, p / (p + _gamma(lw)), torch.zeros_like(p))
    torch.testing.assert_close(out.double(), expect, rtol=0, atol=tol)
    torch.testing.assert_close(out.double(), f.double(), rtol=0, atol=tol + 1e-11)  # P >= 0.33: gamma / P tiny
    # the classical filter too (nsr > 0 is required; 1e-300 is the vanishing limit)
    for nsr in (1e-300, 1e-12):
        torch.testing.assert_close(classical_wiener(f, _otf("identity", dtype), nsr).double(), f.double(),
                                   rtol=0, atol=tol + 1e-11)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("gamma", [1e12, 1e30])
@pytest.mark.parametrize("otf_kind", OTFS)
def test_huge_gamma_shrinks_to_the_scaled_correlation(dtype, gamma, otf_kind):
    f = _inputs(dtype)
    otf = _otf(otf_kind, dtype)
    lw = _learnable(gamma, dtype)
    out = lw(f, otf).detach().double()
    # out = (P / gamma) F^-1{Y conj(H)} up to a relative |H|^2 P / gamma <= 1e-12
    corr = torch.fft.irfft2(torch.fft.rfft2(f.double(), norm="ortho") * otf.to(torch.complex128).conj(), s=(N, N),
                            norm="ortho")
    expect = _power(f) / _gamma(lw) * corr
    rtol = 1e-5 if dtype == torch.float32 else 1e-10
    torch.testing.assert_close(out, expect, rtol=rtol, atol=rtol * float(expect.abs().max()) + 1e-300)
    assert float(out.abs().max()) <= (1e-11 if gamma == 1e12 else 1e-29)  # -> 0 as gamma grows
    # the classical filter with nsr = gamma: the same with P = 1
    cl = classical_wiener(f, otf, gamma).double()
    torch.testing.assert_close(cl, corr / gamma, rtol=rtol, atol=rtol * float((corr / gamma).abs().max()) + 1e-300)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("gamma", GAMMAS)
@pytest.mark.parametrize("otf_kind", OTFS)
def test_constant_image_closed_form(dtype, gamma, otf_kind):
    """Every OTF here has H(0) = 1 (normalized blur): a constant image c is only DC, out = c^3 / (c^2 + gamma)."""
    c = 0.7
    f = torch.full((1, C, N, N), c, dtype=dtype)
    otf = _otf(otf_kind, dtype)
    assert complex(otf[0, 0]) == pytest.approx(1.0, abs=1e-7)
    lw = _learnable(gamma, dtype)
    out = lw(f, otf).detach().double()
    expect = (c**3 / (c**2 + _gamma(lw))).expand_as(out)
    tol = 2e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(out, expect, rtol=tol, atol=tol * 1e-30)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("gamma", GAMMAS)
def test_dc_only_otf_gives_the_scaled_mean(dtype, gamma):
    f = _inputs(dtype)
    lw = _learnable(gamma, dtype)
    out = lw(f, _otf("dc_only", dtype)).detach().double()
    p = _power(f)
    gain = torch.where(p > 0, p / (p + _gamma(lw)), torch.zeros_like(p))
    expect = (f.double().mean(dim=(-2, -1), keepdim=True) * gain).expand_as(out)
    tol = 2e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(out, expect, rtol=tol, atol=tol * float(expect.abs().max()) + 1e-300)


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-4), (torch.float64, 1e-10)])
def test_zero_gamma_with_exact_otf_zeros_is_the_pseudo_inverse(dtype, tol):
    """y = box blur of x; with noise 0 the filter inverts every frequency the box passes and outputs nothing
    where it vanishes: out = x projected onto the box's passband. (Before the fix this was 0/0 = NaN.)"""
    otf = _otf("box_exact", dtype)
    zero = otf == 0
    assert int(zero.sum()) > 0
    x = _inputs(torch.float64)[0]
    y = torch.fft.irfft2(torch.fft.rfft2(x) * otf.to(torch.complex128), s=(N, N)).to(dtype)
    expect = torch.fft.irfft2(torch.where(zero.to(torch.bool), 0, torch.fft.rfft2(x)), s=(N, N))
    for out in (wiener_filter(y, otf, 1.0, 0.0), _learnable(0.0, dtype)(y[None], otf)[0].detach()):
        assert bool(torch.isfinite(out).all())
        torch.testing.assert_close(out.double(), expect, rtol=0, atol=tol)
        assert float(torch.fft.rfft2(out.double())[:, zero].abs().max()) <= tol * N


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("nsr", [1e-300, 1e-45, 1e-30])
@pytest.mark.parametrize("otf_kind", ["box_exact", "dc_only"])
def test_classical_wiener_with_a_vanishing_nsr_is_finite(dtype, nsr, otf_kind):
    """nsr > 0 is all classical_wiener asks; 1e-300 is 0 in float32 and 1e-45 is float32's smallest subnormal.
    Before the fix both gave NaN everywhere in float32 (0 / 0 at the OTF zeros; complex / real division forms
    1 / nsr, which overflows), while float64 was finite."""
    y = _inputs(dtype)
    out = classical_wiener(y, _otf(otf_kind, dtype), nsr)
    assert out.dtype == dtype and bool(torch.isfinite(out).all())
    if otf_kind == "dc_only":  # the mean survives, every other frequency is removed
        expect = y.double().mean(dim=(-2, -1), keepdim=True).expand_as(out)
        torch.testing.assert_close(out.double(), expect, rtol=0, atol=1e-5 if dtype == torch.float32 else 1e-12)


@pytest.mark.parametrize("nsr", [0.0, -1e-30, -1.0, float("nan")])
def test_classical_wiener_rejects_a_non_positive_nsr(nsr):
    y, otf = _inputs(torch.float64), _otf("box", torch.float64)
    with pytest.raises(ValueError, match=f"^nsr must be > 0, got {re.escape(str(nsr))}$"):
        classical_wiener(y, otf, nsr)


def test_gamma_min_keeps_float32_gradients_finite_as_rho_runs_away():
    """What training can reach: rho -> -inf (softplus underflows) leaves gamma = gamma_min = 1e-8, where float32
    outputs and gradients stay finite even on an OTF with round-off zeros and a zero-power feature."""
    lw = LearnableWiener(C, gamma_init=1e-2)  # default gamma_min
    with torch.no_grad():
        lw.rho.fill_(-1e4)
    assert torch.equal(lw.gamma, torch.full((C,), 1e-8))
    f = _inputs(torch.float32).requires_grad_(True)
    out = lw(f, _otf("box", torch.float32))
    gf, grho = torch.autograd.grad(out.square().sum(), (f, lw.rho))
    assert bool(torch.isfinite(out).all()) and bool(torch.isfinite(gf).all()) and bool(torch.isfinite(grho).all())
    assert float(gf.abs().max()) > 0  # (d gamma / d rho = sigmoid(rho) = 0 here: rho's gradient is exactly 0)
