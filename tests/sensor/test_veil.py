"""The out-of-window veil: energy a mask scatters beyond the optics window returns as a uniform veil of the
scene's mean radiance, so that a uniform scene keeps its brightness through any phase mask (BSR = 1)."""
from __future__ import annotations

import pytest
import torch

from codesign.optics.masks import HalfRingMask
from codesign.sensor.simulator import psf_state

from . import _util as U


@pytest.mark.parametrize("path", ["direct", "full"])
def test_uniform_scene_keeps_alpha_b_through_the_coded_mask(path):
    coded, _, _ = U.states(U.ODD)
    assert float(coded.psf.sum()) < 0.9  # this small window loses a lot: the veil has real work to do
    sim = U.make_sim(U.ODD, 33, 11, padded_size=15, path=path, background_veil=True)
    out = sim(U.uniform_scene(sim), U.params(alpha_b=0.6), coded, seed=0)
    torch.testing.assert_close(out["irradiance"], torch.full_like(out["irradiance"], 0.6), rtol=1e-12, atol=1e-12)
    # and the window model alone gives alpha_b * sum(h) / sum(h0) = alpha_b * BSR(window)
    off = U.make_sim(U.ODD, 33, 11, padded_size=15, path=path, background_veil=False)
    irr = off(U.uniform_scene(off), U.params(alpha_b=0.6), coded, seed=0)["irradiance"]
    bsr = float(coded.psf.sum()) / coded.uncoded_energy
    torch.testing.assert_close(irr, torch.full_like(irr, 0.6 * bsr), rtol=1e-12, atol=1e-12)


def test_veil_is_the_missing_energy_times_the_scene_mean():
    coded, _, _ = U.states(U.ODD)
    on = U.make_sim(U.ODD, 33, 11, padded_size=15, background_veil=True)
    off = U.make_sim(U.ODD, 33, 11, padded_size=15, background_veil=False)
    scene = U.random_scene(on)
    a = on(scene, U.params(alpha_b=1.0), coded, seed=0)["irradiance"]
    b = off(scene, U.params(alpha_b=1.0), coded, seed=0)["irradiance"] * coded.uncoded_energy
    veil = (1 - coded.psf.sum()) * scene.mean()
    torch.testing.assert_close(a - b, torch.full_like(a, float(veil)), rtol=1e-10, atol=1e-12)


def test_veil_passes_gradients_to_the_mask():
    sysm, spec = U.system(U.ODD), U.optics(U.ODD)
    mask = HalfRingMask(sysm.grid, spec.aperture_diameter_m)
    sim = U.make_sim(U.ODD, 33, 11, padded_size=15, background_veil=True)
    scene = U.random_scene(sim)
    state = psf_state(sysm, mask.phase())
    out = sim(scene, U.params(alpha_b=1.0), state, seed=0)
    # a uniform veil adds (1 - E_w) mean(b) everywhere: its derivative is -d E_w / d r times the mean
    out["irradiance"].mean().backward()
    assert mask.r.grad is not None and bool(torch.isfinite(mask.r.grad).all())
    assert float(mask.r.grad.abs().sum()) > 0


def test_default_config_has_the_veil_on():
    from codesign.sensor.spec import SensorSpec

    assert SensorSpec().background_veil is True
