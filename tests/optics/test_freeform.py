"""Freeform masks: per-pixel phase and the Zernike basis."""
from __future__ import annotations

import math

import pytest
import torch

from codesign.errors import ConfigError
from codesign.optics import OpticalSystem, OpticsSpec, PixelPhaseMask, ZernikeMask, build_mask, metrics
from codesign.optics.masks import published_halfring
from codesign.optics.masks.zernike import noll_to_nm, zernike
from tests.tolerances import assert_within_ulps

W_A = 3.83e-3


@pytest.fixture(scope="module")
def system64():
    return OpticalSystem(OpticsSpec.with_samples_across(64, focal_n=64), dtype=torch.float64)


@pytest.fixture(scope="module")
def fine_grid():
    return OpticalSystem(OpticsSpec.with_samples_across(256, focal_n=64), dtype=torch.float64).grid


def _outside(grid) -> torch.Tensor:
    out = torch.ones(grid.n * grid.n, dtype=torch.bool)
    out[grid.support] = False
    return out.reshape(grid.n, grid.n)


# ---- pixel phase ----------------------------------------------------------------------------------------------
def test_pixel_mask_reproduces_init_phase_on_support(system64):
    g = system64.grid
    published = published_halfring(g, W_A).phase().detach()
    mask = PixelPhaseMask(g, published)
    assert mask.values.numel() == g.support.numel()
    assert mask.values.requires_grad
    phase = mask.phase()
    torch.testing.assert_close(phase.reshape(-1)[g.support], published.reshape(-1)[g.support], rtol=0, atol=0)
    assert float(phase.detach()[_outside(g)].abs().max()) == 0.0
    torch.testing.assert_close(system64.psf(phase.detach()), system64.psf(published), rtol=0, atol=0)


def test_pixel_mask_init_values_outside_support_are_ignored(system64):
    g = system64.grid
    init = torch.randn(g.n, g.n, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    init[_outside(g)] = float("nan")  # never read
    mask = PixelPhaseMask(g, init)
    assert bool(torch.isfinite(mask.phase()).all())


def test_pixel_mask_zero_init(system64):
    mask = PixelPhaseMask(system64.grid)
    assert float(mask.phase().detach().abs().max()) == 0.0


def test_pixel_mask_bad_init(system64):
    g = system64.grid
    with pytest.raises(ValueError, match=rf"mask\.init phase has shape \(3, 3\), the pupil grid is {g.n} x {g.n}"):
        PixelPhaseMask(g, torch.zeros(3, 3, dtype=torch.float64))
    bad = torch.zeros(g.n, g.n, dtype=torch.float64)
    bad[g.n // 2, g.n // 2] = float("inf")
    with pytest.raises(ValueError, match="mask.init phase holds NaN or Inf inside the aperture"):
        PixelPhaseMask(g, bad)


def test_pixel_project_wraps_without_changing_the_field(system64):
    g = system64.grid
    init = torch.randn(g.n, g.n, dtype=torch.float64, generator=torch.Generator().manual_seed(5)) * 40
    init.reshape(-1)[g.support[:4]] = torch.tensor([math.pi, -math.pi, 3 * math.pi, 0.0], dtype=torch.float64)
    mask = PixelPhaseMask(g, init)
    before = mask.phase().detach().clone()
    mask.project()
    after = mask.phase().detach()
    vals = mask.values.detach()
    assert bool(((vals >= -math.pi) & (vals < math.pi)).all())
    assert float(vals.abs().max()) > 3  # it did not just shrink everything
    f0, f1 = torch.polar(g.aperture, before), torch.polar(g.aperture, after)
    assert float((f0 - f1).abs().max()) <= 1e-12
    torch.testing.assert_close(system64.psf(after), system64.psf(before), rtol=1e-9, atol=1e-15)
    # idempotent
    mask.project()
    assert_within_ulps(mask.phase().detach(), after, 2, scale=math.pi)  # one more wrap into [-pi, pi)


def test_gradcheck_pixel_phase_to_smooth_lsr(tiny_system64):
    system = tiny_system64
    g = system.grid
    mask = PixelPhaseMask(g, published_halfring(g, W_A).phase().detach())
    h0 = system.uncoded_peak

    def lsr(values):
        phase = torch.func.functional_call(mask, {"values": values}, ())
        return metrics.lsr_smooth(system.psf(phase, mask.plate_cell_m), h0, p=16.0)

    values = mask.values.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lsr, (values,), eps=1e-6, atol=1e-8, rtol=1e-4)
    # the module path gives the same gradient
    loss = metrics.lsr_smooth(system.mask_psf(mask), h0, p=16.0)
    loss.backward()
    (g_ref,) = torch.autograd.grad(lsr(values), values)
    torch.testing.assert_close(mask.values.grad, g_ref, rtol=1e-12, atol=1e-15)


# ---- Zernike --------------------------------------------------------------------------------------------------
NOLL = [(0, 0), (1, 1), (1, -1), (2, 0), (2, -2), (2, 2), (3, -1), (3, 1), (3, -3), (3, 3),
        (4, 0), (4, 2), (4, -2), (4, 4), (4, -4)]


def test_noll_to_nm_table():
    assert [noll_to_nm(j) for j in range(1, 16)] == NOLL


def test_noll_to_nm_covers_each_mode_once():
    seen = [noll_to_nm(j) for j in range(1, 67)]  # degrees 0..10
    assert len(set(seen)) == len(seen) == 66
    for n, m in seen:
        assert abs(m) <= n and (n - abs(m)) % 2 == 0
    with pytest.raises(ValueError, match="Noll index must be >= 1"):
        noll_to_nm(0)


def test_low_order_zernike_formulas():
    rho = torch.tensor([0.0, 0.3, 0.7, 1.0], dtype=torch.float64)
    ang = torch.tensor([0.2, 1.0, -2.0, 3.0], dtype=torch.float64)
    torch.testing.assert_close(zernike(0, 0, rho, ang), torch.ones(4, dtype=torch.float64))
    torch.testing.assert_close(zernike(1, 1, rho, ang), 2 * rho * torch.cos(ang))
    torch.testing.assert_close(zernike(1, -1, rho, ang), 2 * rho * torch.sin(ang))
    torch.testing.assert_close(zernike(2, 0, rho, ang), math.sqrt(3) * (2 * rho**2 - 1))
    torch.testing.assert_close(zernike(3, 1, rho, ang), math.sqrt(8) * (3 * rho**3 - 2 * rho) * torch.cos(ang))
    torch.testing.assert_close(zernike(4, 0, rho, ang), math.sqrt(5) * (6 * rho**4 - 6 * rho**2 + 1))


def test_zernike_mask_tip_tilt_axes(fine_grid):
    z = ZernikeMask(fine_grid, W_A, n_terms=3)
    R = W_A / 2
    u = fine_grid.u[None, :].expand(fine_grid.n, fine_grid.n).reshape(-1)[fine_grid.support]
    v = fine_grid.v[:, None].expand(fine_grid.n, fine_grid.n).reshape(-1)[fine_grid.support]
    torch.testing.assert_close(z.basis[1], 2 * u / R, rtol=0, atol=1e-12)  # Z2 = 2 rho cos = tilt along u
    torch.testing.assert_close(z.basis[2], 2 * v / R, rtol=0, atol=1e-12)  # Z3 = 2 rho sin = tilt along v


@pytest.mark.parametrize("n_terms", [15, 36])
def test_zernike_basis_is_orthonormal_on_the_unit_disk(fine_grid, n_terms):
    z = ZernikeMask(fine_grid, W_A, n_terms=n_terms)
    assert z.basis.shape == (n_terms, fine_grid.support.numel())
    rho = fine_grid.rho.reshape(-1)[fine_grid.support] / (W_A / 2)
    inside = rho <= 1
    b = z.basis[:, inside]
    gram = b @ b.T / inside.sum()
    err = float((gram - torch.eye(n_terms, dtype=torch.float64)).abs().max())
    assert err <= 1.5e-2, f"max |<Z_i Z_j> - delta_ij| = {err:.3g}"


def test_zernike_fit_recovers_coefficients(system64):
    g = system64.grid
    c = torch.randn(21, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    src = ZernikeMask(g, W_A, n_terms=21, init_coeffs=c)
    phase = src.phase().detach()
    fitted = ZernikeMask(g, W_A, n_terms=21)
    fitted.fit(phase)
    torch.testing.assert_close(fitted.coeffs.detach(), c, rtol=0, atol=1e-9)
    assert fitted.summary() == pytest.approx({f"zernike_{j + 1}": float(v) for j, v in enumerate(c)}, abs=1e-9)


def test_zernike_project_clamps_coefficients(system64):
    c = torch.tensor([100.0, -100.0, 3.0, -60.0], dtype=torch.float64)
    z = ZernikeMask(system64.grid, W_A, n_terms=4, init_coeffs=c, max_coeff_rad=50.0)
    z.project()
    assert z.coeffs.detach().tolist() == [50.0, -50.0, 3.0, -50.0]


def test_zernike_bad_inputs(system64):
    g = system64.grid
    with pytest.raises(ConfigError, match=r"^mask\.n_terms = 0: must be an integer >= 1"):
        ZernikeMask(g, W_A, n_terms=0)
    with pytest.raises(ConfigError, match=r"^mask\.max_coeff_rad = 0\.0: must be a finite number > 0"):
        ZernikeMask(g, W_A, max_coeff_rad=0.0)
    with pytest.raises(ValueError, match=r"mask\.init_coeffs has 3 values, n_terms = 4"):
        ZernikeMask(g, W_A, n_terms=4, init_coeffs=torch.zeros(3))


def test_gradcheck_zernike_coefficients_to_smooth_lsr(tiny_system64):
    system = tiny_system64
    mask = ZernikeMask(system.grid, W_A, n_terms=10)

    def lsr(c):
        phase = torch.func.functional_call(mask, {"coeffs": c}, ())
        return metrics.lsr_smooth(system.psf(phase), system.uncoded_peak, p=16.0)

    c = (0.5 * torch.randn(10, dtype=torch.float64, generator=torch.Generator().manual_seed(2))).requires_grad_(True)
    assert torch.autograd.gradcheck(lsr, (c,), eps=1e-6, atol=1e-8, rtol=1e-4)


# ---- builder ----------------------------------------------------------------------------------------------------
def test_build_freeform_pixel_published(system64):
    g = system64.grid
    mask = build_mask({"kind": "freeform", "basis": "pixel", "init": "published", "init_convention": "atan"}, g, W_A)
    assert isinstance(mask, PixelPhaseMask)
    ref = published_halfring(g, W_A, convention="atan").phase().detach()
    torch.testing.assert_close(mask.phase().detach(), ref, rtol=0, atol=0)
    zero = build_mask({"kind": "freeform", "init": "zero"}, g, W_A)
    assert float(zero.phase().detach().abs().max()) == 0.0


def test_build_freeform_zernike_fits_published(system64):
    g = system64.grid
    mask = build_mask({"kind": "freeform", "basis": "zernike", "init": "published", "n_terms": 10}, g, W_A)
    assert isinstance(mask, ZernikeMask) and mask.coeffs.numel() == 10
    assert bool(torch.isfinite(mask.coeffs).all())
    assert float(mask.coeffs.detach().abs().sum()) > 0


@pytest.mark.parametrize("cfg,pattern", [
    ({"kind": "freeform", "basis": "spline"}, r"^mask\.basis = 'spline': must be one of pixel, zernike"),
    ({"kind": "freeform", "init": "random"}, r"^mask\.init = 'random': must be one of published, zero"),
    ({"kind": "freeform", "r": [1.0]}, r"^mask\.r = \[1\.0\]: unknown key for a freeform mask; allowed: basis, "
                                       r"defocus_rad, init, init_convention, kind, levels, max_coeff_rad, n_terms"),
    ({"kind": "freeform", "basis": "zernike", "init": "zero", "n_terms": 2.5},
     r"^mask\.n_terms = 2\.5: must be an integer"),
])
def test_build_freeform_errors(system64, cfg, pattern):
    with pytest.raises(ConfigError, match=pattern):
        build_mask(cfg, system64.grid, W_A)
