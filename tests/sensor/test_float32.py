"""Float32 safety: strong lasers (alpha_l up to 1e8) must not produce NaN/Inf, and away from the laser's footprint
a float32 simulation must match the float64 one (same seed; the noise is drawn in float64 for both)."""
from __future__ import annotations

import math

import pytest
import torch

from codesign.sensor.simulator import PSFState
from . import _util as U

ALPHAS = [0.0, 1.0, 1e2, 1e4, 1e6, 1e8]
N, R = 22, 66  # bin factor 3: coarse kernel 11 px, so the footprint leaves most of the 22 x 22 sensor
# laser centre (row, col) in network pixels; equal offsets so the test does not depend on the axis convention
POSITIONS = {"centre": None, "edge": (21.0, 21.0), "outside": (30.0, 30.0), "subpixel": (7.3, 7.3),
             "corner_cut": (-3.0, -3.0)}


def _finite(out: dict) -> None:
    for k, v in out.items():
        if v.is_floating_point():
            assert bool(torch.isfinite(v).all()), f"non-finite values in {k}"


def _box(centre: float, half: int) -> tuple[int, int]:
    c = int(torch.round(torch.tensor(centre, dtype=torch.float64)))  # same rounding as the simulator
    return c - half, c + half


def _footprint(sim, pos, path: str) -> torch.Tensor:
    """Boolean (N, N) map of the network pixels a laser centred at ``pos`` (None: on the axis) can touch."""
    mask = torch.zeros(N, N, dtype=torch.bool)
    k = R // N
    if pos is None:
        pos = ((N - 1) / 2, (N - 1) / 2)
    if path == "direct":  # footprint-size square of network pixels around the rounded centre
        (r0, r1), (c0, c1) = (_box(v, sim.footprint_size(sim.coarse) // 2) for v in pos)
    else:  # footprint-size square of sensor pixels around the rounded fine centre, mapped to network pixels
        fine = [(v - (N - 1) / 2) * k + (R - 1) / 2 for v in pos]
        (r0, r1), (c0, c1) = (_box(v, sim.footprint_size(sim.fine) // 2) for v in fine)
        r0, r1, c0, c1 = math.floor(r0 / k), math.floor(r1 / k), math.floor(c0 / k), math.floor(c1 / k)
    r0, c0, r1, c1 = max(r0, 0), max(c0, 0), min(r1, N - 1), min(c1, N - 1)
    if r0 <= r1 and c0 <= c1:
        mask[r0:r1 + 1, c0:c1 + 1] = True
    return mask


@pytest.mark.parametrize("path", ["direct", "full"])
@pytest.mark.parametrize("where", list(POSITIONS))
def test_float32_matches_float64_outside_the_laser_footprint(path, where):
    sims = {dt: U.make_sim(U.ODD, R, N, path=path) for dt in (torch.float32, torch.float64)}
    sim = sims[torch.float64]
    pos = POSITIONS[where]
    angle = 0.0 if pos is None else U.laser_angle(sim, *pos)
    scene64 = U.random_scene(sim, batch=len(ALPHAS), seed=4)
    alphas = torch.tensor(ALPHAS, dtype=torch.float64)
    outs = {}
    for dt in (torch.float32, torch.float64):
        coded, _, _ = U.states(U.ODD, dt)
        p = U.params(len(ALPHAS), dtype=dt, alpha_b=0.6, laser_angle_rad=angle, **U.NOISY).replace(
            alpha_l=alphas.to(dt))
        outs[dt] = sims[dt](scene64.to(dt), p, coded, seed=11)
        _finite(outs[dt])
        assert outs[dt]["sensor_dn"].dtype == dt
    o32, o64 = outs[torch.float32], outs[torch.float64]
    away = ~_footprint(sim, pos, path)
    assert int(away.sum()) > N * N // 3
    for i, a in enumerate(ALPHAS):
        d = (o32["sensor_dn"][i, 0].double() - o64["sensor_dn"][i, 0])[away]
        assert float(d.abs().max()) <= 1.0, f"alpha_l={a:g}: float32 differs by {float(d.abs().max()):.3g} DN"
        assert torch.equal(o32["saturated"][i, 0][away], o64["saturated"][i, 0][away]), f"alpha_l={a:g}"
        # no laser light outside the footprint, in either precision
        for o in (o32, o64):
            assert torch.equal(o["laser"][i, 0][away], torch.zeros_like(o["laser"][i, 0][away]))
        if a > 0 and where != "outside":
            assert float(o64["laser"][i, 0].max()) > 0  # the laser does land inside the footprint
    if where != "outside":
        # the strongest lasers saturate their core in both precisions
        assert bool(o32["saturated"][-1].any()) and bool(o64["saturated"][-1].any())
        core = o64["laser"][-1, 0] > 2.0
        assert torch.equal(o32["saturated"][-1, 0][core], o64["saturated"][-1, 0][core])


@pytest.mark.parametrize("path", ["direct", "full"])
@pytest.mark.parametrize("alpha_b", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("scene_kind", ["black", "white", "random"])
@pytest.mark.parametrize("exposure", [1e-4, 0.1, 1.0])
def test_float32_outputs_are_finite(path, alpha_b, scene_kind, exposure):
    sim = U.make_sim(U.ODD, 33, 11, path=path)
    coded, _, _ = U.states(U.ODD, torch.float32)
    if scene_kind == "random":
        scene = U.random_scene(sim, batch=2, dtype=torch.float32)
    else:
        scene = U.uniform_scene(sim, 0.0 if scene_kind == "black" else 1.0, batch=2, dtype=torch.float32)
    p = U.params(2, dtype=torch.float32, alpha_b=alpha_b, exposure_s=exposure, **U.NOISY).replace(
        alpha_l=torch.tensor([0.0, 1e6]))
    out = sim(scene, p, coded, seed=0)
    _finite(out)
    s = sim.sensor
    assert float(out["sensor_dn"].min()) >= 0 and float(out["sensor_dn"].max()) <= s.saturation_dn


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
