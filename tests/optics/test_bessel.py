"""J_0..J_n of codesign.optics.bessel against scipy.special.jv, its gradient, and its input checks."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import special

from codesign.optics.bessel import bessel_j, bessel_mix, bessel_rows
from tests.tolerances import assert_within_ulps

N_MAX = 60


def _switch_points(n_max: int) -> list[float]:
    return [1.0, 25.0, float(max(25, n_max + 2))]


def _x_grid(n_max: int, uniform: int = 4001) -> np.ndarray:
    """The arguments of the checks: ``uniform`` points over [0, 1000] (benchmarks/bench_accuracy.py asks for more at
    its full scale), log-spaced from 1e-6, around the algorithm's switch points and near the turning points."""
    pts = [0.0, 1e-300, 1e-12, 1e-8, 1e-3, 0.5, 0.999999, 999.0, 1000.0]
    pts += list(np.linspace(0.0, 1000.0, uniform))
    pts += list(np.geomspace(1e-6, 1000.0, 400))
    for s in _switch_points(n_max):
        pts += list(s + np.linspace(-1e-3, 1e-3, 41))
        pts += list(s + np.array([-1e-9, -1e-12, 0.0, 1e-12, 1e-9]))
        pts += list(s + np.linspace(-2.0, 2.0, 81))
    # near the turning points x ~ n, where J_n changes from evanescent to oscillatory
    pts += list(np.linspace(0.0, 80.0, 1601))
    x = np.unique(np.clip(np.asarray(pts, dtype=np.float64), 0.0, 1000.0))
    return x


def _reference(x: np.ndarray, n_max: int) -> np.ndarray:
    return special.jv(np.arange(n_max + 1)[None, :], x[:, None])


# max |J_n(x) - scipy.special.jv(n, x)| over the grid and the orders 0..n_max (benchmarks/bench_accuracy.py reports
# the measured maxima next to these)
BESSEL_ATOL = {torch.float64: 1e-10, torch.float32: 1e-5}


def _bessel_and_errors(n_max: int, dtype: torch.dtype, uniform: int = 4001):
    """(x grid, bessel_j at x rounded to dtype, |bessel_j - scipy| as float64 with the reference at the rounded
    arguments)."""
    x = _x_grid(n_max, uniform)
    xt = torch.from_numpy(x).to(dtype)
    got = bessel_j(xt, n_max)
    ref = _reference(xt.numpy().astype(np.float64), n_max)
    return x, got, np.abs(got.numpy().astype(np.float64) - ref)


def bessel_error(n_max: int, dtype: torch.dtype = torch.float64, uniform: int = 4001) -> float:
    """max |bessel_j(x, n_max) - scipy.special.jv| over the test grid, in dtype (the reference at the arguments
    rounded to dtype)."""
    return float(_bessel_and_errors(n_max, dtype, uniform)[2].max())


N_MAX_CASES = [1, 2, 10, 35, 36, N_MAX]


@pytest.mark.parametrize("n_max", N_MAX_CASES)
def test_bessel_float64_matches_scipy_to_1e10(n_max):
    x, got, err = _bessel_and_errors(n_max, torch.float64)
    assert got.dtype == torch.float64
    assert got.shape == (x.size, n_max + 1)
    assert np.isfinite(got.numpy()).all()
    i, n = np.unravel_index(np.argmax(err), err.shape)
    assert err.max() <= BESSEL_ATOL[torch.float64], f"max |error| {err.max():.3e} at x = {x[i]!r}, n = {n}"


def test_bessel_float32_matches_scipy_to_1e5():
    _, got, err = _bessel_and_errors(N_MAX, torch.float32)
    assert got.dtype == torch.float32
    assert np.isfinite(got.numpy()).all()
    assert err.max() <= BESSEL_ATOL[torch.float32]


def test_bessel_at_zero_and_tiny_arguments_is_exact():
    x = torch.tensor([0.0, 1e-300, 1e-12], dtype=torch.float64)
    j = bessel_j(x, N_MAX)
    assert torch.isfinite(j).all()
    assert torch.equal(j[0], torch.cat([torch.ones(1, dtype=torch.float64), torch.zeros(N_MAX, dtype=torch.float64)]))
    assert abs(float(j[1, 0]) - 1.0) == 0.0
    assert abs(float(j[2, 0]) - 1.0) <= 1e-20
    assert abs(float(j[2, 1]) - 5e-13) <= 1e-25
    assert (j[1:, 2:].abs() <= 1e-23).all()


def test_bessel_keeps_input_shape():
    x = torch.rand(3, 4, 5, dtype=torch.float64) * 50
    j = bessel_j(x, 7)
    assert j.shape == (3, 4, 5, 8)
    ref = _reference(x.reshape(-1).numpy(), 7).reshape(3, 4, 5, 8)
    np.testing.assert_allclose(j.numpy(), ref, atol=1e-12, rtol=0)


def test_bessel_empty_input():
    j = bessel_j(torch.zeros(0, dtype=torch.float64), 5)
    assert j.shape == (0, 6)


def _jprime(x: np.ndarray, n_max: int) -> np.ndarray:
    n = np.arange(n_max + 1)[None, :]
    xx = x[:, None]
    d = 0.5 * (special.jv(n - 1, xx) - special.jv(n + 1, xx))
    d[:, 0] = -special.jv(1, x)
    return d


# max |dJ_n/dx - (J_{n-1} - J_{n+1}) / 2| (scipy) over every seventh grid point and every order 0..N_MAX
BESSEL_GRADIENT_ATOL = {torch.float64: 1e-10, torch.float32: 1e-5}


def _gradient_setup(dtype: torch.dtype):
    """(x: every seventh grid point in dtype, requiring grad; J_0..J_N_MAX at x; the scipy derivative at x)."""
    x = torch.from_numpy(_x_grid(N_MAX)[::7]).to(dtype).requires_grad_(True)
    return x, bessel_j(x, N_MAX), _jprime(x.detach().numpy().astype(np.float64), N_MAX)


def bessel_gradient_errors(dtype: torch.dtype) -> np.ndarray:
    """Per order n = 0..N_MAX: max over x of |autograd dJ_n/dx - (J_{n-1} - J_{n+1}) / 2|, inf where the gradient
    is not finite."""
    x, j, ref = _gradient_setup(dtype)
    errs = np.empty(N_MAX + 1)
    for n in range(N_MAX + 1):
        (g,) = torch.autograd.grad(j[:, n].sum(), x, retain_graph=True)
        errs[n] = np.abs(g.numpy().astype(np.float64) - ref[:, n]).max() if torch.isfinite(g).all() else np.inf
    return errs


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_bessel_gradient_matches_recurrence_derivative(dtype):
    tol = BESSEL_GRADIENT_ATOL[dtype]
    for n, err in enumerate(bessel_gradient_errors(dtype)):  # inf: a non-finite gradient
        assert err <= tol, f"order {n}: max |dJ/dx error| = {err:.3e}"
    # all orders at once, with random weights
    x, j, ref = _gradient_setup(dtype)
    w = torch.randn(N_MAX + 1, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    (g,) = torch.autograd.grad((j * w.to(dtype)).sum(), x)
    np.testing.assert_allclose(g.numpy().astype(np.float64), ref @ w.numpy(), atol=tol * 20, rtol=0)


GRADCHECK_X0 = [0.3, 0.9, 3.7, 24.0, 30.5, 61.0, 70.0, 640.0]
BESSEL_GRADCHECK_TOL = dict(eps=1e-6, atol=1e-7, rtol=1e-6)  # torch.autograd.gradcheck's eps, atol, rtol


def bessel_gradcheck_case(x0: float):
    """(function, inputs) of the float64 gradcheck at x0 and 0.97 x0."""
    x = torch.tensor([x0, x0 * 0.97], dtype=torch.float64, requires_grad=True)
    return (lambda t: bessel_j(t, N_MAX)), (x,)


@pytest.mark.parametrize("x0", GRADCHECK_X0)
def test_bessel_gradcheck_float64(x0):
    assert torch.autograd.gradcheck(*bessel_gradcheck_case(x0), **BESSEL_GRADCHECK_TOL)


def test_bessel_gradient_at_zero_is_finite():
    x = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    j = bessel_j(x, 4)
    (g,) = torch.autograd.grad(j.sum(), x)
    # d/dx [J0 + J1 + J2 + J3 + J4] at 0 = -J1(0) + (J0 - J2)/2 + ... = 1/2
    assert_within_ulps(g, torch.full_like(g, 0.5), 8, scale=1.0)  # a sum of five terms of order 1


@pytest.mark.parametrize("bad", [[-1.0], [1.0, -1e-300], [float("nan")], [2.0, float("nan"), 3.0]])
def test_bessel_rejects_negative_or_nan(bad):
    with pytest.raises(ValueError, match="x must be >= 0 and not NaN"):
        bessel_j(torch.tensor(bad, dtype=torch.float64), 3)


@pytest.mark.parametrize("dtype", [torch.int64, torch.int32, torch.bool, torch.complex128])
def test_bessel_rejects_non_real_floating_dtype(dtype):
    with pytest.raises(ValueError, match="x must be a real floating tensor"):
        bessel_j(torch.ones(3, dtype=dtype), 3)


@pytest.mark.parametrize("n_max", [0, -1, 201, 2.0, "3", None])
def test_bessel_rejects_n_max_out_of_range(n_max):
    with pytest.raises(ValueError, match=r"n_max must be an integer in \[1, 200\]"):
        bessel_j(torch.ones(3, dtype=torch.float64), n_max)


def test_bessel_accepts_n_max_200():
    x = torch.tensor([0.5, 10.0, 150.0, 210.0, 999.0], dtype=torch.float64)
    j = bessel_j(x, 200)
    ref = _reference(x.numpy(), 200)
    assert np.abs(j.numpy() - ref).max() <= 1e-10


def _mix_reference(x: torch.Tensor, w: torch.Tensor, orders) -> torch.Tensor:
    """The same sums through bessel_j (whole orders 0..max, autograd through its gather and products)."""
    full = bessel_j(x, max(max(orders), 1))  # (R, U, N + 1)
    return torch.stack([(w[:, k, None] * full[..., n]).sum(0) for k, n in enumerate(orders)])


def test_bessel_mix_equals_the_weighted_sum_of_bessel_j_and_its_gradients():
    """The half-ring's outputs (J_0, then each odd order 3..35 twice), ascending rows spanning the three regimes
    (the in-place runs), the same rows shuffled (the gather/scatter path), and short rows (concatenated runs)."""
    orders = [0] + list(range(3, 36, 2)) * 2
    gen = torch.Generator().manual_seed(3)
    w = torch.randn(3, len(orders), dtype=torch.float64, generator=gen)
    rows = torch.linspace(0.0, 300.0, 40000, dtype=torch.float64) * torch.tensor([[1.0], [0.4], [0.07]])
    for x0 in (rows, rows[:, torch.randperm(40000, generator=gen)], rows[:, ::400].contiguous()):
        x = x0.clone().requires_grad_(True)
        wt = w.clone().requires_grad_(True)
        got = bessel_mix(x, wt, orders)
        ref = _mix_reference(x, wt, orders)
        assert got.shape == (len(orders), x.shape[1])
        torch.testing.assert_close(got, ref, rtol=0, atol=1e-12)
        g = torch.randn(got.shape, dtype=torch.float64, generator=gen)
        for a, b in zip(torch.autograd.grad((got * g).sum(), (x, wt)), torch.autograd.grad((ref * g).sum(), (x, wt))):
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(got[1].detach().numpy(), (w[:, 1, None].numpy() * special.jv(3, x0.numpy())).sum(0),
                               rtol=0, atol=1e-10)


def test_bessel_rows_runs_and_scatter_paths_agree_to_rounding():
    """Same recurrences either way; only the last bits of a few elements may differ (vectorized and scalar tails
    of the elementwise math differ in rounding, by one ulp on the CPUs seen so far)."""
    x = torch.linspace(0.0, 200.0, 70001, dtype=torch.float64)
    perm = torch.randperm(x.numel(), generator=torch.Generator().manual_seed(4))
    ordered = bessel_rows(x, range(38))
    shuffled = bessel_rows(x[perm], range(38))  # too many regime runs: the gather / scatter path
    assert_within_ulps(shuffled, ordered[:, perm], 2)


def test_bessel_mix_gradcheck_and_input_checks():
    x = torch.tensor([[0.3, 2.0, 17.0, 40.0, 120.0], [0.01, 0.9, 5.0, 26.0, 39.0]], dtype=torch.float64,
                     requires_grad=True)
    w = torch.tensor([[0.5, -1.0, 2.0], [1.5, 0.25, -0.75]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t, v: bessel_mix(t, v, (0, 5, 5)), (x, w), eps=1e-6, atol=1e-9)
    with pytest.raises(ValueError, match=r"orders must be integers in \[0, 200\], got \(0, 201, 1\)"):
        bessel_mix(x, w, (0, 201, 1))
    with pytest.raises(ValueError, match=r"x must be \(R, U\) and weights \(R, 2\) \(one column per order\); got "
                                         r"x \(2, 5\), weights \(2, 3\)"):
        bessel_mix(x, w, (0, 1))
    with pytest.raises(ValueError, match=r"x must be >= 0 and not NaN"):
        bessel_mix(-x, w, (0, 1, 2))


def test_bessel_mix_reuses_its_table_only_when_no_graph_holds_it():
    """Two forwards before either backward: the second must not overwrite the table the first one's backward
    reads (the workspace hands out a new table while a graph holds the old one)."""
    x = torch.linspace(0.0, 80.0, 50000, dtype=torch.float64).reshape(2, 25000)
    w1 = torch.tensor([[1.0, 0.5], [-0.25, 2.0]], dtype=torch.float64, requires_grad=True)
    (alone,) = torch.autograd.grad(bessel_mix(x, w1, (3, 7)).sum(), w1)
    first = bessel_mix(x, w1, (3, 7))
    second = bessel_mix(x * 0.5, w1, (3, 7))  # same table shape, other values
    (g_first,) = torch.autograd.grad(first.sum(), w1)
    (g_second,) = torch.autograd.grad(second.sum(), w1)
    assert torch.equal(g_first, alone)
    assert not torch.allclose(g_second, alone)
