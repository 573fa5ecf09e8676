"""Gradients from the sensor output back to the half-ring parameters (r, theta), float64.

The reparameterized noise is a deterministic function of the PSF for a fixed seed, so the direct path (smooth
apart from the full-well clamp, which these settings stay clear of) is gradchecked with every noise term on.
"""
from __future__ import annotations

from functools import lru_cache

import pytest
import torch

from codesign.optics import HalfRingMask, OpticalSystem, OpticsSpec
from codesign.optics.masks import PUBLISHED_R, PUBLISHED_THETA
from codesign.sensor.simulator import SensorSimulator, psf_state
from codesign.sensor.spec import SensorSpec
from . import _util as U

TINY_N = 15  # focal window; with resolution 24, image_size 8 (bin factor 3) the coarse kernel is 5 px = 15 dx


@lru_cache(maxsize=None)
def _tiny():
    spec = OpticsSpec.with_samples_across(24, focal_n=TINY_N)
    return spec, OpticalSystem(spec, dtype=torch.float64)


def _sim(path: str, resolution: int = 24, image_size: int = 8) -> SensorSimulator:
    spec, _ = _tiny()
    return SensorSimulator(SensorSpec(resolution=resolution, image_size=image_size, padded_size=image_size + 2,
                                      path=path), spec)


def _pipeline(sim: SensorSimulator, p, scene: torch.Tensor, key: str = "sensor", seed: int = 5):
    spec, system = _tiny()
    mask = HalfRingMask(system.grid, spec.aperture_diameter_m)

    def run(r, theta):
        phase = torch.func.functional_call(mask, {"r": r, "theta": theta}, ())
        return sim(scene, p, psf_state(system, phase), seed=seed)

    return run


def _inputs():
    r = torch.tensor(PUBLISHED_R, dtype=torch.float64, requires_grad=True)
    theta = torch.tensor(PUBLISHED_THETA, dtype=torch.float64, requires_grad=True)
    return r, theta


GRADCHECK_TOL = dict(eps=1e-6, atol=1e-8, rtol=1e-4)  # torch.autograd.gradcheck's eps, atol, rtol


def direct_path_gradcheck_case():
    """(the direct-path pipeline (r, theta) -> outputs, the scalar sum(w * sensor) of (r, theta), the published
    (r, theta)): two samples, laser on the sensor, every noise term on, fixed seed."""
    sim = _sim("direct")
    scene = U.random_scene(sim, batch=2, seed=3)
    p = U.params(2, alpha_b=0.5, alpha_l=20.0, laser_angle_rad=U.laser_angle(sim, 3.3, 3.3), **U.NOISY)
    run = _pipeline(sim, p, scene)
    w = torch.randn(2, 1, 10, 10, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def f(r, theta):
        return (run(r, theta)["sensor"] * w).sum()

    return run, f, _inputs()


def test_gradcheck_direct_path_with_every_noise_term_on():
    run, f, inputs = direct_path_gradcheck_case()
    r0, t0 = _inputs()
    out = run(r0, t0)
    assert not bool(out["saturated"].any())  # the full-well clamp is not active: the map is smooth
    assert float(out["laser"].detach().max()) > 0.05  # the laser contributes
    assert torch.autograd.gradcheck(f, inputs, **GRADCHECK_TOL)


@pytest.mark.parametrize("path", ["direct", "full"])
def test_gradient_reaches_the_ring_parameters_through_the_laser(path):
    sim = _sim(path)
    scene = U.random_scene(sim, seed=1)
    p = U.params(alpha_b=0.4, alpha_l=50.0, laser_angle_rad=U.laser_angle(sim, 4.2, 4.2), **U.NOISY)
    r, theta = _inputs()
    out = _pipeline(sim, p, scene)(r, theta)
    loss = (out["sensor"] ** 2).sum() + out["laser"].sum()
    gr, gt = torch.autograd.grad(loss, (r, theta))
    for g in (gr, gt):
        assert bool(torch.isfinite(g).all())
        assert float(g.abs().max()) > 0
    # and through the laser alone (no background)
    out = _pipeline(sim, p.replace(alpha_b=0.0), scene)(r, theta)
    (gr,) = torch.autograd.grad(out["sensor"].sum(), r)
    assert bool(torch.isfinite(gr).all()) and float(gr.abs().max()) > 0


@pytest.mark.parametrize("path,resolution,image_size", [("direct", 24, 8), ("full", 10, 10)])
def test_saturated_pixels_pass_no_gradient(path, resolution, image_size):
    """A strong laser saturates part of the sensor: those pixels carry no signal, hence no gradient."""
    sim = _sim(path, resolution, image_size)
    scene = U.random_scene(sim, seed=2)
    n = image_size
    p = U.params(alpha_b=0.5, alpha_l=3e3, laser_angle_rad=U.laser_angle(sim, n / 2 - 0.3, n / 2 - 0.3),
                 **U.NOISY)
    r, theta = _inputs()
    out = _pipeline(sim, p, scene)(r, theta)
    sat = out["saturated"]
    assert 0 < int(sat.sum()) < sat.numel()
    dn = out["sensor_dn"]
    g_sat = torch.autograd.grad(dn[sat].sum(), (r, theta), retain_graph=True)
    g_lin = torch.autograd.grad(dn[~sat].sum(), (r, theta))
    for g in g_sat:
        assert torch.equal(g, torch.zeros_like(g))
    assert float(g_lin[0].abs().max()) > 0 and float(g_lin[1].abs().max()) > 0


def test_gradient_is_finite_on_a_black_scene_without_laser():
    """mu_p = 0 everywhere: sqrt of the photon variance must not produce NaN gradients."""
    sim = _sim("direct")
    scene = U.uniform_scene(sim, 0.0)
    p = U.params(alpha_b=0.5, alpha_l=0.0, **U.NOISY)
    r, theta = _inputs()
    out = _pipeline(sim, p, scene)(r, theta)
    gr, gt = torch.autograd.grad(out["sensor"].sum(), (r, theta), allow_unused=True)
    for g in (gr, gt):
        assert g is None or bool(torch.isfinite(g).all())
