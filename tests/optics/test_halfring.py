"""The five half-ring mask: evaluation strategies, conventions, symmetry, input checks, projection, gradients."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import special

from codesign.errors import ConfigError
from codesign.optics import OpticalSystem, OpticsSpec, RadialMTF, metrics
from codesign.optics.masks import PUBLISHED_R, PUBLISHED_THETA, HalfRingMask, build_mask, published_halfring

W_A = 3.83e-3


def _wrap(x: torch.Tensor) -> torch.Tensor:
    """Into [-pi, pi)."""
    return torch.remainder(x + math.pi, 2 * math.pi) - math.pi


def _on_support(mask_or_grid, phase: torch.Tensor) -> torch.Tensor:
    grid = getattr(mask_or_grid, "grid", mask_or_grid)
    return phase.reshape(-1)[grid.support]


def _reference_phase(grid, r, theta, m_range=(1, 17), convention="atan2", harmonic_sign="printed") -> np.ndarray:
    """Eq. (PhaseFunc) written out directly with scipy's J_n, at the support samples (float64)."""
    rho = grid.rho.reshape(-1)[grid.support].numpy().astype(np.float64)
    ang = grid.angle.reshape(-1)[grid.support].numpy().astype(np.float64)
    q0 = np.zeros_like(rho)
    im = np.zeros_like(rho)
    for rn, tn in zip(r, theta):
        x = 2 * np.pi * rho * rn / W_A
        q0 += rn * special.jv(0, x)
        for m in range(m_range[0], m_range[1] + 1):
            mo = 2 * m + 1
            a = 4 * rn / (mo * np.pi)
            if harmonic_sign == "fourier":
                a *= (-1) ** m
            im += a * np.sin(mo * (ang - tn)) * special.jv(mo, x)
    return np.arctan2(im, q0) if convention == "atan2" else np.arctan(im / q0)


@pytest.fixture(scope="module")
def grid64():
    return OpticalSystem(OpticsSpec.with_samples_across(64, focal_n=64), dtype=torch.float64).grid


@pytest.fixture(scope="module")
def grid32():
    return OpticalSystem(OpticsSpec.with_samples_across(32, focal_n=32), dtype=torch.float64).grid


def test_grid_angle_convention(grid64):
    c = grid64.n // 2
    # Phi = atan2(u, v): 0 on the +v axis (rows), pi/2 on the +u axis (columns)
    assert float(grid64.angle[c + 5, c]) == 0.0
    assert float(grid64.angle[c, c + 5]) == pytest.approx(math.pi / 2, abs=1e-15)
    assert float(grid64.angle[c, c - 5]) == pytest.approx(-math.pi / 2, abs=1e-15)
    assert float(grid64.angle[c - 5, c]) == pytest.approx(math.pi, abs=1e-15)


def grid64_float64():
    """The grid64 fixture's grid, for callers outside pytest (benchmarks/bench_accuracy.py)."""
    return OpticalSystem(OpticsSpec.with_samples_across(64, focal_n=64), dtype=torch.float64).grid


# ---- strategies and the equation itself ---------------------------------------------------------------------
CONVENTIONS, HARMONIC_SIGNS = ["atan2", "atan"], ["printed", "fourier"]
EXACT_DIRECT_TOL = 1e-11  # max |exact - direct| phase over the window (wrapped), rad
FLOAT32_PHASE_RMS_TOL = 1e-4  # RMS |float32 - float64| phase on the support (wrapped), rad


def _exact_and_direct(grid, convention: str, harmonic_sign: str) -> tuple[torch.Tensor, torch.Tensor]:
    kw = dict(convention=convention, harmonic_sign=harmonic_sign)
    return tuple(HalfRingMask(grid, W_A, strategy=st, **kw).phase().detach() for st in ("exact", "direct"))


def exact_direct_error(convention: str, harmonic_sign: str, phases=None) -> float:
    """max over the window of |exact - direct| (wrapped) of the published half ring on grid64 (``phases``: the
    (exact, direct) pair, computed when not given)."""
    exact, direct = _exact_and_direct(grid64_float64(), convention, harmonic_sign) if phases is None else phases
    return float(_wrap(exact - direct).abs().max())


@pytest.mark.parametrize("convention", CONVENTIONS)
@pytest.mark.parametrize("harmonic_sign", HARMONIC_SIGNS)
def test_exact_strategy_equals_direct(grid64, convention, harmonic_sign):
    exact, direct = _exact_and_direct(grid64, convention, harmonic_sign)
    assert exact.dtype == torch.float64 and exact.shape == (grid64.n, grid64.n)
    assert exact_direct_error(convention, harmonic_sign, (exact, direct)) <= EXACT_DIRECT_TOL  # measured 4e-13
    # zero outside the support
    outside = torch.ones(grid64.n * grid64.n, dtype=torch.bool)
    outside[grid64.support] = False
    assert float(exact.reshape(-1)[outside].abs().max()) == 0.0


@pytest.mark.parametrize("convention", ["atan2", "atan"])
@pytest.mark.parametrize("harmonic_sign", ["printed", "fourier"])
@pytest.mark.parametrize("m_range", [(1, 17), (0, 17), (0, 0), (2, 5)])
def test_phase_matches_equation_written_with_scipy(grid32, convention, harmonic_sign, m_range):
    mask = HalfRingMask(grid32, W_A, m_range=m_range, convention=convention, harmonic_sign=harmonic_sign)
    got = _on_support(mask, mask.phase().detach())
    ref = torch.from_numpy(_reference_phase(grid32, PUBLISHED_R, PUBLISHED_THETA, m_range, convention,
                                            harmonic_sign))
    assert float(_wrap(got - ref).abs().max()) <= 1e-10
    assert torch.equal(mask.orders, torch.arange(2 * m_range[0] + 1, 2 * m_range[1] + 2, 2))


def test_single_ring_first_order_is_analytic(grid32):
    # one ring, m_range (0, 0): phi = atan2((4/pi) sin(Phi - theta) J1(x), J0(x))
    r, th = 7.5, 0.4
    mask = HalfRingMask(grid32, W_A, r=[r], theta=[th], m_range=(0, 0), strategy="direct")
    rho = _on_support(grid32, grid32.rho)
    ang = _on_support(grid32, grid32.angle)
    x = (2 * math.pi * r / W_A * rho).numpy()
    ref = np.arctan2(4 / np.pi * np.sin(ang.numpy() - th) * special.j1(x), special.j0(x))
    got = _on_support(mask, mask.phase().detach())
    assert float(_wrap(got - torch.from_numpy(ref)).abs().max()) <= 1e-12


def test_table_strategy_is_close_to_exact(grid64):
    exact = _on_support(grid64, HalfRingMask(grid64, W_A, strategy="exact").phase().detach())
    table = _on_support(grid64, HalfRingMask(grid64, W_A, strategy="table", table_size=4096).phase().detach())
    err = _wrap(table - exact).abs()
    # measured: max 0.021 rad, RMS 7.7e-4 rad (linear interpolation of J_35 profiles at the largest ring)
    assert float(err.max()) <= 0.05
    assert float(err.pow(2).mean().sqrt()) <= 2e-3
    coarse = _on_support(grid64, HalfRingMask(grid64, W_A, strategy="table", table_size=256).phase().detach())
    assert float(_wrap(coarse - exact).pow(2).mean().sqrt()) > float(err.pow(2).mean().sqrt())


def _float32_and_float64_phases():
    """(float32 phase, float64 phase, float64 grid) of the published half ring, 64 samples across."""
    spec = OpticsSpec.with_samples_across(64, focal_n=64)
    g32 = OpticalSystem(spec, dtype=torch.float32).grid
    g64 = OpticalSystem(spec, dtype=torch.float64).grid
    return HalfRingMask(g32, W_A).phase().detach(), HalfRingMask(g64, W_A).phase().detach(), g64


def float32_phase_rms(phases=None) -> float:
    """RMS over the support of |float32 phase - float64 phase| (wrapped), rad."""
    p32, p64, g64 = _float32_and_float64_phases() if phases is None else phases
    err = _wrap(p32.double() - p64).reshape(-1)[g64.support].abs()
    return float(err.pow(2).mean().sqrt())


def test_exact_strategy_float32_close_to_float64():
    phases = _float32_and_float64_phases()
    assert phases[0].dtype == torch.float32
    assert float32_phase_rms(phases) <= FLOAT32_PHASE_RMS_TOL


# ---- conventions --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("harmonic_sign", ["printed", "fourier"])
def test_convention_ranges_and_relation(grid64, harmonic_sign):
    p2 = _on_support(grid64, HalfRingMask(grid64, W_A, convention="atan2", harmonic_sign=harmonic_sign).phase()
                     .detach())
    p1 = _on_support(grid64, HalfRingMask(grid64, W_A, convention="atan", harmonic_sign=harmonic_sign).phase()
                     .detach())
    assert float(p1.min()) >= -math.pi / 2 and float(p1.max()) <= math.pi / 2
    assert float(p2.min()) > -math.pi and float(p2.max()) <= math.pi
    assert float(p2.max() - p2.min()) > 3 * math.pi / 2  # atan2 uses the full circle
    # atan is atan2 modulo pi: the difference is 0 or +-pi
    d = _wrap(p2 - p1)
    k = torch.round(d / math.pi)
    assert float((d - k * math.pi).abs().max()) <= 1e-12
    assert set(k.unique().tolist()) <= {-1.0, 0.0, 1.0}
    assert bool((k == 0).any()) and bool((k != 0).any())


def test_published_halfring_is_frozen_and_default(grid64):
    m = published_halfring(grid64, W_A)
    assert not any(p.requires_grad for p in m.parameters())
    ref = HalfRingMask(grid64, W_A)
    torch.testing.assert_close(m.phase(), ref.phase().detach(), rtol=0, atol=0)
    assert m.summary() == pytest.approx({**{f"r_{i + 1}": v for i, v in enumerate(PUBLISHED_R)},
                                         **{f"theta_{i + 1}": v for i, v in enumerate(PUBLISHED_THETA)}})


# ---- rotation ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("quarter_turns", [1, 2, 3])
@pytest.mark.parametrize("strategy", ["exact", "direct"])
def test_rotating_all_theta_rotates_the_phase(grid64, quarter_turns, strategy):
    delta = quarter_turns * math.pi / 2
    n, c = grid64.n, grid64.n // 2
    base = HalfRingMask(grid64, W_A, strategy=strategy).phase().detach()
    turned = HalfRingMask(grid64, W_A, theta=[t + delta for t in PUBLISHED_THETA],
                          strategy=strategy).phase().detach()
    # phase_{theta + delta}(Phi + delta) == phase_theta(Phi). A +pi/2 turn of Phi = atan2(u, v) maps (u, v) to
    # (v, -u): sample [row i, col j] goes to [row 2c - j, col i].
    i, j = grid64.support // n, grid64.support % n
    for _ in range(quarter_turns):
        i, j = 2 * c - j, i
    got = turned[i, j]
    want = base.reshape(-1)[grid64.support]
    assert float(_wrap(got - want).abs().max()) <= 1e-10
    # and it is not trivially invariant
    assert float(_wrap(base.reshape(-1)[grid64.support] - turned.reshape(-1)[grid64.support]).abs().max()) > 0.1


# ---- input checks -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs,pattern", [
    (dict(r=[1.0, 2.0], theta=[0.1]), r"^mask\.theta = \[0\.1\]: must have the same length as mask\.r \(2 values\)"),
    (dict(r=[], theta=[]), r"^mask\.theta = \[\]: must have the same length as mask\.r \(0 values\) and at least one"),
    (dict(r=[1.0, 0.0], theta=[0.1, 0.2]), r"^mask\.r\[1\] = 0\.0: must be a finite number > 0"),
    (dict(r=[-2.0], theta=[0.1]), r"^mask\.r\[0\] = -2\.0: must be a finite number > 0"),
    (dict(r=[1.0], theta=[float("nan")]), r"^mask\.theta\[0\] = nan: must be a finite number"),
    (dict(m_range=(5, 2)), r"^mask\.m_range\[1\] = 2: must be an integer >= 5 and <= 99"),
    (dict(m_range=(-1, 2)), r"^mask\.m_range\[0\] = -1: must be an integer >= 0 and <= 99"),
    (dict(m_range=(1, 2, 3)), r"^mask\.m_range = \[1, 2, 3\]: must be \[m_min, m_max\]"),
    (dict(convention="atan3"), r"^mask\.convention = 'atan3': must be one of atan, atan2"),
    (dict(harmonic_sign="alternating"), r"^mask\.harmonic_sign = 'alternating': must be one of printed, fourier"),
    (dict(strategy="fast"), r"^mask\.strategy = 'fast': must be one of exact, table, direct"),
    (dict(table_size=8), r"^mask\.table_size = 8: must be an integer >= 16"),
    (dict(r_bounds=(5.0, 1.0)), r"^mask\.r_bounds = \[5\.0, 1\.0\]: must be \[lo, hi\] with 0 < lo < hi"),
    (dict(r_bounds=(0.0, 1.0)), r"^mask\.r_bounds\[0\] = 0\.0: must be a finite number > 0"),
])
def test_bad_halfring_inputs_name_the_key(grid32, kwargs, pattern):
    with pytest.raises(ConfigError, match=pattern):
        HalfRingMask(grid32, W_A, **kwargs)


def test_bad_halfring_prefix_and_aperture(grid32):
    with pytest.raises(ConfigError, match=r"^model\.mask\.convention = 'x'"):
        HalfRingMask(grid32, W_A, convention="x", prefix="model.mask")
    with pytest.raises(ConfigError, match=r"^optics\.aperture_diameter_m = 0\.0: must be a finite number > 0"):
        HalfRingMask(grid32, 0.0)


@pytest.mark.parametrize("cfg,pattern", [
    ({"kind": "vortex2"}, r"^mask\.kind = 'vortex2': must be one of halfring, pixel, spiral, spline, zernike, freeform"),
    ({"kind": "halfring", "preset": "published", "colour": 1}, r"^mask\.colour = 1: unknown key for a halfring mask; allowed: "),
    ({"kind": "halfring", "preset": "published", "r": [1.0], "theta": [0.0]},
     r"^mask\.preset = 'published': cannot be combined with explicit mask\.r / mask\.theta"),
    ({"kind": "halfring", "preset": None, "r": [1.0]}, r"^mask\.r = \[1\.0\]: mask\.r and mask\.theta are required"),
    ({"kind": "halfring", "preset": "other"}, r"^mask\.preset = 'other': must be one of published"),
    ({"kind": "halfring", "preset": "published", "convention": "tan"}, r"^mask\.convention = 'tan'"),
])
def test_build_mask_errors(grid32, cfg, pattern):
    with pytest.raises(ConfigError, match=pattern):
        build_mask(cfg, grid32, W_A)


def test_build_mask_halfring_from_config(grid32):
    cfg = {"kind": "halfring", "preset": None, "r": [3.0, 5.0], "theta": [0.5, 1.0], "m_range": [0, 4],
           "convention": "atan", "harmonic_sign": "fourier", "strategy": "direct", "table_size": 64,
           "r_bounds": [1.0, 50.0]}
    mask = build_mask(cfg, grid32, W_A)
    assert isinstance(mask, HalfRingMask)
    assert mask.convention == "atan" and mask.harmonic_sign == "fourier" and mask.strategy == "direct"
    assert mask.r_bounds == (1.0, 50.0)
    ref = _reference_phase(grid32, [3.0, 5.0], [0.5, 1.0], (0, 4), "atan", "fourier")
    got = _on_support(mask, mask.phase().detach())
    assert float(_wrap(got - torch.from_numpy(ref)).abs().max()) <= 1e-10


# ---- projection ---------------------------------------------------------------------------------------------
def test_project_clamps_r_and_wraps_theta(grid32):
    mask = HalfRingMask(grid32, W_A, r=[0.1, 5.0, 300.0, 200.0], theta=[-0.5, 7.0, 2 * math.pi, 1.0],
                        r_bounds=(0.5, 200.0))
    before = mask.phase().detach()
    mask.project()
    assert mask.r.tolist() == pytest.approx([0.5, 5.0, 200.0, 200.0], abs=0)
    th = mask.theta.detach()
    assert bool(((th >= 0) & (th < 2 * math.pi)).all())
    torch.testing.assert_close(th, torch.tensor([2 * math.pi - 0.5, 7.0 - 2 * math.pi, 0.0, 1.0],
                                                dtype=torch.float64), rtol=0, atol=1e-14)
    assert mask.r.requires_grad and mask.theta.requires_grad  # still parameters after the in-place clamp
    # wrapping theta by 2 pi does not change the phase (only odd harmonics of theta appear)
    only_wrap = HalfRingMask(grid32, W_A, r=[0.5, 5.0, 200.0, 200.0], theta=[-0.5, 7.0, 2 * math.pi, 1.0])
    torch.testing.assert_close(_wrap(mask.phase().detach() - only_wrap.phase().detach()),
                               torch.zeros_like(before), rtol=0, atol=1e-9)


# ---- gradients ----------------------------------------------------------------------------------------------
def _phase_fn(mask):
    def phase(r, theta):
        return torch.func.functional_call(mask, {"r": r, "theta": theta}, ())

    return phase


@pytest.fixture(scope="module")
def tiny(tiny_spec, tiny_system64):
    return tiny_spec, tiny_system64


def _inputs(n=5):
    r = torch.tensor(PUBLISHED_R[:n], dtype=torch.float64, requires_grad=True)
    theta = torch.tensor(PUBLISHED_THETA[:n], dtype=torch.float64, requires_grad=True)
    return r, theta


@pytest.mark.parametrize("strategy", ["exact", "table", "direct"])
@pytest.mark.parametrize("convention", ["atan2", "atan"])
def test_gradcheck_field_of_ring_parameters(tiny, strategy, convention):
    spec, system = tiny
    mask = HalfRingMask(system.grid, W_A, strategy=strategy, convention=convention, table_size=256)
    phase = _phase_fn(mask)

    def field(r, theta):
        p = phase(r, theta)
        return torch.cos(p), torch.sin(p)

    assert torch.autograd.gradcheck(field, _inputs(), eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


LSR_GRADCHECK_TOL = dict(eps=1e-6, atol=1e-7, rtol=1e-4)  # torch.autograd.gradcheck's eps, atol, rtol


def lsr_gradcheck_case(convention: str, harmonic_sign: str, system: OpticalSystem | None = None):
    """(smooth LSR (p = 16) as a function of (r, theta), the published (r, theta)) on the tiny system (the
    tiny_system64 fixture of tests/conftest.py, built when not given)."""
    if system is None:
        system = OpticalSystem(OpticsSpec.with_samples_across(24, focal_n=32), dtype=torch.float64)
    mask = HalfRingMask(system.grid, W_A, convention=convention, harmonic_sign=harmonic_sign)
    phase = _phase_fn(mask)
    h0 = system.uncoded_peak

    def lsr(r, theta):
        return metrics.lsr_smooth(system.psf(phase(r, theta)), h0, p=16.0)

    return lsr, _inputs()


@pytest.mark.parametrize("convention", CONVENTIONS)
@pytest.mark.parametrize("harmonic_sign", HARMONIC_SIGNS)
def test_gradcheck_ring_parameters_to_smooth_lsr(tiny, convention, harmonic_sign):
    spec, system = tiny
    assert torch.autograd.gradcheck(*lsr_gradcheck_case(convention, harmonic_sign, system), **LSR_GRADCHECK_TOL)


def test_gradcheck_ring_parameters_to_mtf_summary(tiny):
    spec, system = tiny
    mask = HalfRingMask(system.grid, W_A)
    phase = _phase_fn(mask)
    radial = RadialMTF(spec)

    def mtf_summary(r, theta):
        rad = radial(metrics.mtf(system.psf(phase(r, theta))))
        mean, mn = radial.summary(rad, (0.0, 0.5))
        return mean, mn

    assert torch.autograd.gradcheck(mtf_summary, _inputs(), eps=1e-6, atol=1e-7, rtol=1e-4)


def test_backward_through_module_parameters(tiny):
    spec, system = tiny
    mask = HalfRingMask(system.grid, W_A)
    loss = metrics.lsr_smooth(system.psf(mask.phase()), system.uncoded_peak, p=16.0)
    loss.backward()
    assert mask.r.grad is not None and mask.theta.grad is not None
    assert bool(torch.isfinite(mask.r.grad).all()) and bool(torch.isfinite(mask.theta.grad).all())
    assert float(mask.r.grad.abs().sum()) > 0 and float(mask.theta.grad.abs().sum()) > 0


@pytest.mark.slow
def test_exact_strategy_equals_direct_at_paper_sampling():
    # Table 1 sampling: 1068 x 1068 grid, ~9 s for the direct reference on 2 cores
    from codesign.optics.grid import PupilGrid

    spec = OpticsSpec(pupil_pitch_m=3.74e-6)
    grid = PupilGrid.from_spec(spec, dtype=torch.float64)
    exact = HalfRingMask(grid, W_A).phase().detach()
    direct = HalfRingMask(grid, W_A, strategy="direct").phase().detach()
    assert float(_wrap(exact - direct).abs().max()) <= 1e-10  # measured 1.1e-11


@pytest.mark.parametrize("samples", [47, 64])
def test_octant_sums_equal_the_full_angular_sum_and_its_gradient(samples):
    """OctantSums (the exact strategy) against the per-sample angular sum (direct): odd and even grids, arbitrary
    angles (no symmetry of the mask itself), both harmonic signs, Im and the gradient of the phase."""
    from codesign.optics.grid import PupilGrid

    grid = PupilGrid.from_spec(OpticsSpec.with_samples_across(samples, focal_n=64), dtype=torch.float64)
    for sign in ("printed", "fourier"):
        kw = dict(r=(13.6, 50.0, 6.3), theta=(1.86, 0.37, 4.4), m_range=(0, 17), harmonic_sign=sign)
        exact, direct = HalfRingMask(grid, W_A, strategy="exact", **kw), HalfRingMask(grid, W_A, strategy="direct", **kw)
        (_, im_e), (_, im_d) = exact.field_parts(), direct.field_parts()
        assert float((im_e - im_d).abs().max()) <= 1e-11 * float(im_d.abs().max())
        w = torch.rand(grid.n, grid.n, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
        (exact.phase() * w).sum().backward()
        (direct.phase() * w).sum().backward()
        torch.testing.assert_close(exact.r.grad, direct.r.grad, rtol=1e-8, atol=1e-10)
        torch.testing.assert_close(exact.theta.grad, direct.theta.grad, rtol=1e-8, atol=1e-10)
