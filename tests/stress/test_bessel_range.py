"""Bessel J_n (codesign/optics/bessel.py) over the whole range the optics uses: n = 0..60, x in [0, 1000].

tests/optics/test_bessel.py checks this range at ~6,500 points to 1e-10 and the gradient against the recurrence
(J_{n-1} - J_{n+1}) / 2 written with scipy's J_n. Here: a dense grid (every algorithm switch, every turning point
x ~ n, x = 0 and 1e-12), the tolerances the algorithm actually reaches, relative accuracy where J_n is evanescent,
and the gradient against scipy.special.jvp itself. Measured on the slow level's 220,000 points, n = 0..60: max
|error| 2.8e-14, max relative error 1.5e-13 where n > x; gradient (2,500 points) max |error| 2.5e-14.

Tolerances. |J_n(x)| <= 1 for every n and x, so "absolute error relative to max(1, |J|)" is the absolute error:
1e-13, ~4x the measured 2.8e-14. That is the floor of float64 arithmetic here: the Hankel series and up to ~60
recurrence steps each round at 1.1e-16 of the running magnitude (~60 eps = 7e-15), and scipy's reference carries
its own ~1e-15. Where n > x, J_n is evanescent, J_n ~ (e x / 2n)^n, e.g. J_60(1) = 1.0e-100, and an absolute
tolerance says nothing: there the error relative to |J_n| is asserted, 1e-12 (~7x the measured 1.5e-13; series
and Miller's backward recurrence are relative-accurate there). Below |J| = 1e-280 float64 runs out of exponent
(subnormals and scipy's underflow to 0), so the relative check stops there (the absolute one still holds).
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import special

from codesign.optics import bessel

N_MAX = 60
ABS_TOL = 1e-13
REL_TOL = 1e-12
REL_FLOOR = 1e-280


def _grid(n_dense: int, seed: int) -> np.ndarray:
    """x in [0, 1000]: the special points, a dense uniform grid shifted off round numbers, a log grid down to
    1e-12, points around each algorithm switch, and around every turning point x = n."""
    rng = np.random.default_rng(seed)
    special_pts = [0.0, 1e-300, 1e-12, 1e-8, 1e-3, 999.0, 1000.0]
    switches = [bessel._X_SERIES, bessel._X_ASYMPTOTIC_MIN, bessel._miller_limit(N_MAX)]
    near = [s + d for s in switches for d in (-1e-9, -1e-12, 0.0, 1e-12, 1e-9, -0.5, 0.5)]
    turning = [n + d for n in range(N_MAX + 2) for d in (-0.5, -1e-6, 0.0, 1e-6, 0.5)]
    dense = np.linspace(0.0, 1000.0, n_dense) + rng.uniform(0, 1000.0 / n_dense, n_dense)
    logs = np.geomspace(1e-12, 1000.0, n_dense // 10)
    x = np.concatenate([special_pts, near, turning, dense, logs])
    return np.unique(np.clip(x, 0.0, 1000.0))


def _check_values(x: np.ndarray) -> None:
    got = bessel.bessel_j(torch.from_numpy(x), N_MAX).numpy()
    assert np.isfinite(got).all()
    ref = special.jv(np.arange(N_MAX + 1)[None, :], x[:, None])
    err = np.abs(got - ref)
    i, n = np.unravel_index(np.argmax(err), err.shape)
    assert err.max() <= ABS_TOL, f"max |error| {err.max():.3e} at x = {x[i]!r}, n = {n}"
    evanescent = (np.arange(N_MAX + 1)[None, :] > x[:, None]) & (np.abs(ref) > REL_FLOOR)
    rel = err[evanescent] / np.abs(ref[evanescent])
    assert evanescent.sum() > x.size  # the region is well populated (every x < 60 has orders above it)
    assert rel.max() <= REL_TOL, f"max relative error {rel.max():.3e} where n > x"
    # where scipy underflows to 0, ours is (sub)normal-small, not garbage
    assert np.abs(got[ref == 0]).max(initial=0.0) <= REL_FLOOR


def _check_gradient(x: np.ndarray) -> None:
    xt = torch.from_numpy(x).requires_grad_(True)
    j = bessel.bessel_j(xt, N_MAX)
    ref = special.jvp(np.arange(N_MAX + 1)[None, :], x[:, None])
    for n in range(N_MAX + 1):  # J_n(x_i) depends on x_i only: the gradient of the sum is the derivative
        (g,) = torch.autograd.grad(j[:, n].sum(), xt, retain_graph=n < N_MAX)
        g = g.numpy()
        assert np.isfinite(g).all(), f"order {n}"
        err = np.abs(g - ref[:, n])
        assert err.max() <= ABS_TOL, f"order {n}: max |dJ/dx error| {err.max():.3e} at x = {x[np.argmax(err)]!r}"


def test_bessel_values_on_a_dense_grid():
    _check_values(_grid(8000, seed=0))


def test_bessel_gradient_matches_scipy_jvp():
    x = _grid(2000, seed=1)
    assert 0.0 in x and 1e-12 in x
    _check_gradient(x)


def test_bessel_gradient_at_zero_and_1e_12_is_exact():
    """dJ_n/dx at 0: 1/2 for n = 1, 0 otherwise; at 1e-12 the leading terms -x/2, 1/2 - 3x^2/16, x/4."""
    x = torch.tensor([0.0, 1e-12], dtype=torch.float64, requires_grad=True)
    j = bessel.bessel_j(x, N_MAX)
    grads = torch.stack([torch.autograd.grad(j[:, n].sum(), x, retain_graph=True)[0] for n in range(N_MAX + 1)], 1)
    assert bool(torch.isfinite(grads).all())
    at0 = torch.zeros(N_MAX + 1, dtype=torch.float64)
    at0[1] = 0.5
    assert torch.equal(grads[0], at0)
    t = 1e-12
    torch.testing.assert_close(grads[1, :3], torch.tensor([-t / 2, 0.5 - 3 * t * t / 16, t / 4],
                                                          dtype=torch.float64), rtol=1e-14, atol=0)
    assert float(grads[1, 3:].abs().max()) <= 1e-24  # dJ_3/dx = x^2 / 16 = 6e-26, higher orders smaller


@pytest.mark.slow
def test_bessel_values_on_a_200k_grid():
    _check_values(_grid(200_000, seed=2))


@pytest.mark.slow
def test_bessel_gradient_matches_scipy_jvp_on_a_40k_grid():
    _check_gradient(_grid(40_000, seed=3))
