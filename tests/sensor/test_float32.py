"""Float32 safety of the gradient: a strong laser (alpha_l up to 1e8) leaves the gradient w.r.t. the PSF finite.

The float32-against-float64 sweep over laser strengths and positions is in tests/stress/test_laser_sweep.py, the
finiteness of extreme scenes (black, white, a single bright pixel) in tests/stress/test_extreme_scenes.py."""
from __future__ import annotations

import pytest
import torch

from codesign.sensor.simulator import PSFState
from . import _util as U

N, R = 22, 66  # bin factor 3: coarse kernel 11 px, so the footprint leaves most of the 22 x 22 sensor


def _finite(out: dict) -> None:
    for k, v in out.items():
        if v.is_floating_point():
            assert bool(torch.isfinite(v).all()), f"non-finite values in {k}"


@pytest.mark.parametrize("path", ["direct", "full"])
def test_float32_gradient_is_finite_with_a_huge_laser(path):
    sim = U.make_sim(U.ODD, R, N, path=path)
    coded, _, _ = U.states(U.ODD, torch.float32)
    psf = coded.psf.detach().clone().requires_grad_(True)
    state = PSFState(psf=psf, uncoded_peak=coded.uncoded_peak, uncoded_energy=coded.uncoded_energy)
    for alpha in (1e4, 1e8):
        p = U.params(1, dtype=torch.float32, alpha_b=0.5, alpha_l=alpha,
                     laser_angle_rad=U.laser_angle(sim, 10.3, 10.3), **U.NOISY)
        out = sim(U.random_scene(sim, dtype=torch.float32), p, state, seed=0)
        _finite(out)
        (g,) = torch.autograd.grad(out["sensor"].sum(), psf)
        assert bool(torch.isfinite(g).all())
        assert not bool(out["saturated"].all())
        assert float(g.abs().max()) > 0  # the unsaturated pixels still pass gradient
