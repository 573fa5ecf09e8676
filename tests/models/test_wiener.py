"""Wiener deconvolution (codesign/models/wiener.py) against a numpy float64 reference, and the learnable
feature-space Wiener module G_v's deconv of Eq. (Deconvolution):  f^_i = F^-1{ F_i conj(H) / (|H|^2 + gamma_i /
E|F_i|^2) }, here with E|F_i|^2 = mean(f_i^2) (ortho FFT, Parseval)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.func import functional_call

from codesign.models import classical_wiener, otf_from_kernel, wiener_filter
from codesign.models.wiener import DeconvModule, LearnableWiener


def _gaussian(k: int, sigma: float) -> np.ndarray:
    r = np.arange(k) - k // 2
    g = np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * sigma**2))
    return g / g.sum()


def _np_otf(kernel: np.ndarray, n: int) -> np.ndarray:
    """Full fft2 of the kernel placed on an n x n circular grid with its centre pixel (k // 2, k // 2) at (0, 0)."""
    k = kernel.shape[0]
    big = np.zeros((n, n))
    for i in range(k):
        for j in range(k):
            big[(i - k // 2) % n, (j - k // 2) % n] += kernel[i, j]
    return np.fft.fft2(big)


def _np_wiener(y: np.ndarray, h: np.ndarray, nsr) -> np.ndarray:
    return np.real(np.fft.ifft2(np.fft.fft2(y) * np.conj(h) / (np.abs(h) ** 2 + nsr)))


def _np_blur(x: np.ndarray, h: np.ndarray) -> np.ndarray:
    return np.real(np.fft.ifft2(np.fft.fft2(x) * h))


# Tolerances and the measured errors they bound (benchmarks/bench_accuracy.py reports these errors next to them)
CLASSICAL_SIZES = [20, 21]  # even and odd image sides
CLASSICAL_ATOL = 1e-10  # max |classical_wiener - numpy float64 closed form|
TINY_NSR_ATOL = 1e-8  # max |Wiener(blurred, nsr 1e-12) - unblurred image|, |H| >= 0.2
LEARNABLE_F64_ATOL = 1e-10  # max |G_v deconvolution - numpy closed form|, float64
LEARNABLE_F32_OF_MAX = 2e-5  # the same in float32, as a fraction of max |closed form|


def _classical_case(n: int):
    """(y, kernel, nsr, classical_wiener output, numpy float64 reference) for two n x n images."""
    rng = np.random.default_rng(0)
    kernel = _gaussian(5, 1.2)
    kernel[0, 3] += 0.3                       # asymmetric: conj(H) must be the OTF's conjugate, not H
    y = rng.random((2, n, n))
    nsr = 3e-2
    out = classical_wiener(torch.from_numpy(y), otf_from_kernel(torch.from_numpy(kernel), n), nsr)
    ref = np.stack([_np_wiener(im, _np_otf(kernel, n), nsr) for im in y])
    return y, kernel, nsr, out, ref


def classical_wiener_error(n: int, case: tuple | None = None) -> float:
    """max |classical_wiener - numpy closed form| (``case``: the _classical_case of n, computed when not given)."""
    *_, out, ref = _classical_case(n) if case is None else case
    return float(np.abs(out.numpy() - ref).max())


@pytest.mark.parametrize("n", CLASSICAL_SIZES)
def test_classical_wiener_equals_numpy_reference(n):
    case = _classical_case(n)
    y, kernel, nsr, out, ref = case
    assert out.dtype == torch.float64 and out.shape == y.shape
    assert classical_wiener_error(n, case) <= CLASSICAL_ATOL  # a NaN fails too
    # wiener_filter with power p and noise p * nsr is the same filter
    out2 = wiener_filter(torch.from_numpy(y), otf_from_kernel(torch.from_numpy(kernel), n), 7.0, 7.0 * nsr)
    np.testing.assert_allclose(out2.numpy(), ref, rtol=0, atol=CLASSICAL_ATOL)


def test_otf_from_kernel_dc_and_centring():
    n = 16
    kernel = torch.from_numpy(_gaussian(7, 1.5) * 2.5)
    otf = otf_from_kernel(kernel, n)
    assert otf.shape == (n, n // 2 + 1) and otf.dtype == torch.complex128
    assert otf[0, 0].real.item() == pytest.approx(2.5, abs=1e-13) and abs(otf[0, 0].imag.item()) < 1e-15
    np.testing.assert_allclose(otf.numpy(), _np_otf(kernel.numpy(), n)[:, : n // 2 + 1], rtol=0, atol=1e-13)
    # a symmetric kernel centred on the grid origin has a real OTF (no linear phase = no shift)
    assert otf.imag.abs().max() < 1e-13
    # a centred delta is the identity
    delta = torch.zeros(5, 5, dtype=torch.float64)
    delta[2, 2] = 1.0
    torch.testing.assert_close(otf_from_kernel(delta, n), torch.ones(n, n // 2 + 1, dtype=torch.complex128),
                               rtol=0, atol=1e-15)
    # float32 kernels give a complex64 OTF; batched kernels are supported
    assert otf_from_kernel(delta.float(), n).dtype == torch.complex64
    assert otf_from_kernel(delta.expand(3, 5, 5), n).shape == (3, n, n // 2 + 1)
    with pytest.raises(ValueError):
        otf_from_kernel(torch.ones(9, 9), 8)


def test_off_centre_kernel_is_a_convolution_shift():
    """A PSF whose spot sits (1, 2) px below/right of the kernel centre moves the image by (1, 2)."""
    n = 12
    kernel = torch.zeros(5, 5, dtype=torch.float64)
    kernel[2 + 1, 2 + 2] = 1.0
    x = torch.rand(1, 1, n, n, dtype=torch.float64)
    blurred = torch.fft.irfft2(torch.fft.rfft2(x) * otf_from_kernel(kernel, n), s=(n, n))
    torch.testing.assert_close(blurred, torch.roll(x, (1, 2), dims=(-2, -1)), rtol=0, atol=1e-14)
    # and the Wiener filter (tiny nsr) undoes that shift
    torch.testing.assert_close(classical_wiener(blurred, otf_from_kernel(kernel, n), 1e-12), x, rtol=0, atol=1e-10)


def _tiny_nsr_case():
    """(kernel, its OTF h, image x, blurred y, Wiener(y, nsr = 1e-12)) on a 32 x 32 grid."""
    n = 32
    rng = np.random.default_rng(1)
    kernel = 0.4 * _gaussian(5, 1.0)
    kernel[2, 2] += 0.6                                         # |H| >= 0.2 everywhere
    h = _np_otf(kernel, n)
    x = rng.random((n, n))
    y = _np_blur(x, h)
    out = classical_wiener(torch.from_numpy(y), otf_from_kernel(torch.from_numpy(kernel), n), 1e-12)
    return kernel, h, x, y, out


def tiny_nsr_inversion_error(case: tuple | None = None) -> float:
    """max |Wiener(blurred image, nsr 1e-12) - the image| for a blur with |H| >= 0.2 (``case``: computed when not
    given)."""
    *_, x, _, out = _tiny_nsr_case() if case is None else case
    return float(np.abs(out.numpy() - x).max())


def test_wiener_with_tiny_nsr_inverts_a_well_conditioned_blur():
    case = _tiny_nsr_case()
    kernel, h, x, y, out = case
    n = x.shape[0]
    assert np.abs(h).min() > 0.19
    assert np.abs(y - x).max() > 0.05                          # the blur is visible
    assert out.shape == x.shape
    assert tiny_nsr_inversion_error(case) <= TINY_NSR_ATOL  # a NaN fails too
    # a large nsr shrinks towards zero (regularization): the DC gain is H / (H^2 + nsr) < 1 / H
    out_reg = classical_wiener(torch.from_numpy(y), otf_from_kernel(torch.from_numpy(kernel), n), 1.0)
    assert out_reg.mean().item() == pytest.approx(y.mean() * 1.0 / (1.0 + 1.0), rel=1e-10)
    with pytest.raises(ValueError):
        classical_wiener(torch.from_numpy(y), otf_from_kernel(torch.from_numpy(kernel), n), 0.0)


def _np_learnable(f: np.ndarray, h: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """Eq. (Deconvolution) per feature: Y conj(H) P / (|H|^2 P + gamma), P = mean(f^2)."""
    out = np.empty_like(f)
    for b in range(f.shape[0]):
        for i in range(f.shape[1]):
            p = np.mean(f[b, i] ** 2)
            out[b, i] = _np_wiener(f[b, i], h, gamma[i] / p)
    return out


def _learnable_float32_case():
    """(features, G_v output, numpy float64 closed form): float32 module, distinct gamma and power per feature."""
    n = 16
    torch.manual_seed(0)
    lw = LearnableWiener(3, gamma_init=0.05)
    with torch.no_grad():
        lw.rho.add_(torch.tensor([0.0, 1.0, -2.0]))            # distinct gamma per feature
    f = torch.rand(2, 3, n, n) * torch.tensor([1.0, 0.1, 3.0]).view(1, 3, 1, 1)   # distinct powers
    kernel = _gaussian(5, 1.0)
    out = lw(f, otf_from_kernel(torch.from_numpy(kernel).float(), n))
    ref = _np_learnable(f.double().numpy(), _np_otf(kernel, n), lw.gamma.detach().double().numpy())
    return f, out, ref


def _learnable_float64_case():
    """(features, G_v output, numpy closed form): float64 module."""
    n = 16
    lw = LearnableWiener(3, gamma_init=0.05).double()
    f = torch.rand(2, 3, n, n, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    kernel = _gaussian(5, 1.0)
    out = lw(f, otf_from_kernel(torch.from_numpy(kernel), n))
    ref = _np_learnable(f.numpy(), _np_otf(kernel, n), lw.gamma.detach().numpy())
    return f, out, ref


def learnable_wiener_float32_error(case: tuple | None = None) -> float:
    """max |float32 G_v deconvolution - numpy float64 closed form| / max |closed form| (``case``: computed when not
    given)."""
    _, out, ref = _learnable_float32_case() if case is None else case
    return float(np.abs(out.detach().double().numpy() - ref).max() / np.abs(ref).max())


def learnable_wiener_float64_error(case: tuple | None = None) -> float:
    """max |float64 G_v deconvolution - numpy closed form| (``case``: computed when not given)."""
    _, out, ref = _learnable_float64_case() if case is None else case
    return float(np.abs(out.detach().numpy() - ref).max())


def test_learnable_wiener_closed_form_float32():
    case = _learnable_float32_case()
    f, out, ref = case
    assert out.dtype == torch.float32 and out.shape == f.shape
    assert learnable_wiener_float32_error(case) <= LEARNABLE_F32_OF_MAX  # a NaN fails too


def test_learnable_wiener_closed_form_float64():
    case = _learnable_float64_case()
    f, out, ref = case
    assert out.shape == ref.shape
    assert learnable_wiener_float64_error(case) <= LEARNABLE_F64_ATOL  # a NaN fails too


@pytest.mark.parametrize("gamma_init", [1e-6, 1e-2, 1.0, 100.0])
def test_gamma_is_gamma_init_at_construction_and_stays_positive(gamma_init):
    lw = LearnableWiener(4, gamma_init=gamma_init)
    torch.testing.assert_close(lw.gamma, torch.full((4,), gamma_init), rtol=1e-5, atol=0)
    with torch.no_grad():
        lw.rho.fill_(-1e4)                     # softplus underflows; gamma_min keeps it positive
    assert (lw.gamma > 0).all()
    with torch.no_grad():
        lw.rho.fill_(1e4)
    assert torch.isfinite(lw.gamma).all()
    with pytest.raises(ValueError):
        LearnableWiener(2, gamma_init=1e-9)


def test_learnable_wiener_is_finite_at_zero_power_and_otf_zeros():
    n = 16
    kernel = torch.full((2, 2), 0.25, dtype=torch.float64, requires_grad=True)   # 2x2 box: zeros at Nyquist
    otf = otf_from_kernel(kernel, n)
    zeros = otf.detach().abs() < 1e-12
    assert zeros.any() and zeros[n // 2].all() and zeros[:, n // 2].all()
    otf = torch.where(zeros, torch.zeros_like(otf), otf)        # exact zeros
    lw = LearnableWiener(2, gamma_init=1e-2).double()
    f = torch.rand(1, 2, n, n, dtype=torch.float64)
    f[:, 1] = 0.0                                               # a dead feature channel (ReLU output)
    f.requires_grad_(True)
    out = lw(f, otf)
    assert torch.isfinite(out).all()
    assert torch.count_nonzero(out[:, 1]) == 0                  # P = 0 -> 0
    # nothing is put where the OTF vanishes
    assert torch.fft.rfft2(out[0, 0])[zeros].abs().max() < 1e-12
    (out * torch.randn_like(out)).sum().backward()
    for g in (f.grad, lw.rho.grad, kernel.grad):
        assert g is not None and torch.isfinite(g).all()
    assert f.grad[:, 0].abs().sum() > 0 and kernel.grad.abs().sum() > 0


LEARNABLE_GRADCHECK_TOL = dict(eps=1e-6, atol=1e-5, rtol=1e-3)  # torch.autograd.gradcheck's defaults


def learnable_wiener_gradcheck_case():
    """(G_v as a function of (features, rho), (features, rho)): 2 features, 8 x 8, float64."""
    n = 8
    lw = LearnableWiener(2, gamma_init=0.1).double()
    kernel = torch.from_numpy(_gaussian(3, 0.8))
    otf = otf_from_kernel(kernel, n)
    f = torch.rand(1, 2, n, n, dtype=torch.float64, generator=torch.Generator().manual_seed(5)).requires_grad_()
    rho = lw.rho.detach().clone().requires_grad_()
    return (lambda f, r: functional_call(lw, {"rho": r}, (f, otf))), (f, rho)


def test_learnable_wiener_gradcheck_input_and_rho():
    assert torch.autograd.gradcheck(*learnable_wiener_gradcheck_case(), **LEARNABLE_GRADCHECK_TOL,
                                    raise_exception=False)


def test_learnable_wiener_gradcheck_rho_and_closed_form():
    """What passes today: the gradient w.r.t. rho, and the same closed form written with a float64 power."""
    n = 8
    lw = LearnableWiener(2, gamma_init=0.1).double()
    kernel = torch.from_numpy(_gaussian(3, 0.8)).requires_grad_()
    f = torch.rand(1, 2, n, n, dtype=torch.float64, generator=torch.Generator().manual_seed(5)).requires_grad_()
    rho = lw.rho.detach().clone().requires_grad_()
    otf = otf_from_kernel(kernel.detach(), n)
    assert torch.autograd.gradcheck(lambda r: functional_call(lw, {"rho": r}, (f.detach(), otf)), (rho,))

    def closed_form(f, r, k):
        power = f.square().mean(dim=(-2, -1), keepdim=True)
        gamma = torch.nn.functional.softplus(r) + lw.gamma_min
        return wiener_filter(f, otf_from_kernel(k, n), power, gamma.view(1, -1, 1, 1))

    assert torch.autograd.gradcheck(closed_form, (f, rho, kernel))


def test_deconv_module_shapes():
    torch.manual_seed(0)
    gv = DeconvModule(features=5, kernel=5, gamma_init=0.02)
    otf = otf_from_kernel(torch.from_numpy(_gaussian(5, 1.0)).float(), 24)
    out = gv(torch.rand(2, 1, 24, 24), otf)
    assert out.shape == (2, 5, 24, 24) and torch.isfinite(out).all()
    torch.testing.assert_close(gv.deconv.gamma, torch.full((5,), 0.02), rtol=1e-5, atol=0)
    assert gv.fe.net[0][0].kernel_size == (5, 5)
