"""The physical limit of the LSR / MTF trade: a closed case by hand, the uncoded aperture, and no mask of any family
(random or optimized, >= 200 of them) beyond it."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from codesign.design.limits import MTFLimit
from codesign.optics import OpticalSystem, OpticsSpec, RadialMTF, metrics
from codesign.optics.masks import build_mask

BAND = (0.0, 0.5)


@pytest.fixture(scope="module")
def system():
    return OpticalSystem(OpticsSpec.with_samples_across(64, focal_n=64), dtype=torch.float64)


def _figures(system, mask, band=BAND):
    with torch.no_grad():
        psf = system.psf(mask.phase().to(torch.float64), mask.plate_cell_m)
    radial = RadialMTF(system.spec)
    mean = float(radial.summary(radial(metrics.mtf(psf)), band)[0])
    return float(psf.max()) / system.uncoded_peak, mean, float(psf.sum())


def test_one_ring_band_has_the_closed_form_of_equal_water_levels(system):
    """A band that holds one radial bin (the n_1 frequencies nearest DC): every w_f = 1 / n_1, so below
    saturation the water-filling profile is flat, M_f = t / n_1, its power n_1 (t / n_1)^2 = B and the band mean
    t / n_1: mtf_bound(LSR) = sqrt(B / n_1) with B = m^2 LSR h0(0) - 1 (unit energy)."""
    radial = RadialMTF(system.spec)
    step = float(radial.freqs[1])
    band = (0.5 * step, 1.5 * step)
    n1 = int(radial.counts[1])
    limit = MTFLimit(system, band)
    m, h0 = system.spec.focal_n, system.uncoded_peak
    otf0_min = float(metrics.mtf(system.uncoded_psf().to(torch.float64)).reshape(-1)[radial.bin_index == 1].min())
    for lsr in (1.5 / (m**2 * h0), 3.0 / (m**2 * h0)):
        budget = m**2 * lsr * h0 - 1
        by_hand = math.sqrt(budget / n1)
        assert by_hand < otf0_min  # below saturation: the closed form applies
        assert limit.mtf_bound(lsr) == pytest.approx(by_hand, rel=1e-12)
        assert limit.lsr_limit(by_hand) == pytest.approx(lsr, rel=1e-12)  # the inverse
    # a budget that saturates every frequency gives the uncoded aperture's own band mean
    assert limit.mtf_bound(1.0) == pytest.approx(limit.uncoded_mtf_mean, rel=1e-12)


def test_uncoded_aperture_satisfies_the_bound(system):
    limit = MTFLimit(system, BAND)
    # a smooth family at zero phase (a pixel plate at zero phase is the aperture seen through its cells' envelope)
    mask = build_mask({"kind": "zernike", "init": "zero"}, system.grid, system.spec.aperture_diameter_m)
    lsr, mean, energy = _figures(system, mask)
    assert lsr == pytest.approx(1.0, rel=1e-3)  # the sampled peak is h0(0) itself (the axis is a sample)
    assert mean == pytest.approx(limit.uncoded_mtf_mean, rel=1e-9)
    assert mean <= limit.mtf_bound(lsr, energy) * (1 + 1e-9)
    assert limit.lsr_limit(mean, energy) <= lsr


def _random_masks(system, rng):
    g, d = system.grid, system.spec.aperture_diameter_m
    out = []
    for i in range(40):
        out.append(build_mask({"kind": "halfring", "preset": None, "r": rng.uniform(0.5, 20, 5).tolist(),
                               "theta": rng.uniform(0, 6.28, 5).tolist()}, g, d))
        z = build_mask({"kind": "zernike", "init": "zero", "n_terms": 21}, g, d)
        z.set_vector(torch.from_numpy(rng.normal(0, 2.0 * rng.uniform(0.1, 3), 21)))
        out.append(z)
        out.append(build_mask({"kind": "spiral", "charge": float(rng.uniform(-8, 8)),
                               "axicon_cycles": float(rng.uniform(-8, 8)),
                               "defocus_rad": float(rng.uniform(-30, 30))}, g, d))
        p = build_mask({"kind": "pixel", "init": "zero"}, g, d)
        p.set_vector(p.random_vector(rng) + torch.from_numpy(rng.normal(0, rng.uniform(0, 1.5), p.vector_size)))
        out.append(p)
        s = build_mask({"kind": "spline", "init": "zero"}, g, d)
        s.set_vector(torch.from_numpy(rng.normal(0, rng.uniform(0.5, 6), s.vector_size)))
        out.append(s)
    return out


def test_no_mask_of_any_family_lands_beyond_the_limit(system):
    limit = MTFLimit(system, BAND)
    masks = _random_masks(system, np.random.default_rng(0))
    assert len(masks) >= 200 and {m.kind for m in masks} == {"halfring", "zernike", "spiral", "pixel", "spline"}
    margins = []
    for mask in masks:
        lsr, mean, energy = _figures(system, mask)
        margins.append(limit.mtf_bound(lsr, energy) - mean)
        assert mean <= limit.mtf_bound(lsr, energy) * (1 + 1e-9), (mask.kind, lsr, mean, energy)
        assert lsr >= limit.lsr_limit(mean, energy) * (1 - 1e-9)
    assert min(margins) >= 0


def test_optimized_designs_stay_behind_the_limit(system):
    """Designs pushed hard against it (the search on the pixel and spline families) still respect it."""
    from codesign.design.optimize import run_start
    from codesign.design.problem import DesignProblem, Limits

    limit = MTFLimit(system, BAND)
    radial = RadialMTF(system.spec)
    for kind in ("pixel", "spline"):
        mask = build_mask({"kind": kind, "init": "defocus", "defocus_rad": 12.0}, system.grid,
                          system.spec.aperture_diameter_m)
        _, mean0, _ = _figures(system, mask)
        problem = DesignProblem(system, mask, radial, BAND, "lsr", Limits(mtf=0.8 * mean0, energy=0.95))
        lo, hi = (b.numpy() for b in mask.bounds())
        run_start(problem, "0", mask.to_vector().numpy(), (lo, hi), "AL_LBFGS", None, (16.0, 128.0), 80, 0, 0, 0)
        x, feasible = problem.result_x()
        mask.set_vector(torch.from_numpy(x))
        lsr, mean, energy = _figures(system, mask)
        assert feasible and mean <= limit.mtf_bound(lsr, energy) * (1 + 1e-9)
        assert 1.0 < lsr / limit.lsr_limit(mean, energy) < 50  # behind the limit, and not absurdly far
