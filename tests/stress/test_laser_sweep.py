"""Laser strength x position sweep of the float32 sensor simulation against its float64 reference.

Moved here from tests/sensor/test_float32.py (which kept the gradient check) and extended from five positions to
the grid below, and from six strengths to every decade in the slow level. Same seed in both precisions: the noise
is drawn in float64 and cast (codesign/sensor/noise.py), so every difference is round-off. For every position and
strength: no NaN/Inf in any output; counts in [0, s_sat]; away from the laser's footprint the float32 counts are
within 1 DN of float64, the saturated masks are equal and no laser light lands; and the saturated mask agrees with
the counts (direct path: saturated exactly where a pixel reads G e_sat).

Geometry: bin factor 3 (66 sensor pixels -> 22 network pixels), 33-sample optics window, so the coarse kernel is
11 px and the footprint 13 px: most of the 22 x 22 sensor lies outside it.
"""
from __future__ import annotations

import math

import pytest
import torch

from tests.sensor import _util as U

N, R = 22, 66
K = R // N  # sensor pixels per network pixel along a side
PATHS = ["direct", "full"]
ALPHAS = [0.0, 1.0, 1e2, 1e4, 1e6, 1e8]
ALPHAS_EVERY_DECADE = [0.0] + [10.0**k for k in range(9)]
# laser centre (row, col) in network pixels; None: on the optical axis (angle exactly 0). Row and column differ on
# purpose: the footprint the test predicts then also checks the documented axis convention (n_u along columns).
POSITIONS = {
    "centre": None,                       # between the four central pixels, (10.5, 10.5)
    "pixel_centre": (10.0, 10.0),
    "subpixel": (7.3, 12.8),
    "subpixel_quarter": (13.25, 8.75),
    "edge_corner": (21.0, 21.0),          # centred on the last pixel: three quarters of the footprint are cut off
    "edge_side": (0.0, 10.5),
    "edge_beyond": (-0.4, 4.2),           # centre just outside the first pixel row
    "outside_tail": (26.0, 4.2),          # centre 5 px outside: only the footprint's edge reaches rows 20-21
    "outside": (30.0, 30.0),              # footprint entirely off the sensor: skipped
    "far_outside": (400.0, -250.0),
    "corner_cut": (-3.0, -3.0),
}
# the slow level adds random sub-pixel positions over and around the field
RANDOM_POSITIONS = {f"random_{i}": (round(-6.0 + 34.0 * a, 4), round(-6.0 + 34.0 * b, 4)) for i, (a, b) in
                    enumerate(torch.rand(12, 2, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
                              .tolist())}


def _max(t: torch.Tensor, empty: float = 0.0) -> float:
    return float(t.max()) if t.numel() else empty


def _finite(out: dict) -> None:
    for k, v in out.items():
        if v.is_floating_point():
            assert bool(torch.isfinite(v).all()), f"non-finite values in {k}"


def _box(centre: float, half: int) -> tuple[int, int]:
    c = int(torch.round(torch.tensor(centre, dtype=torch.float64)))  # same rounding as the simulator
    return c - half, c + half


def _centre(pos) -> tuple[float, float]:
    return ((N - 1) / 2, (N - 1) / 2) if pos is None else pos


def _fine(v: float) -> float:
    """Network-pixel coordinate -> sensor-pixel coordinate (both pixel-centre units)."""
    return (v - (N - 1) / 2) * K + (R - 1) / 2


def _footprint(sim, pos, path: str) -> torch.Tensor:
    """Boolean (N, N) map of the network pixels a laser centred at ``pos`` can touch."""
    mask = torch.zeros(N, N, dtype=torch.bool)
    pos = _centre(pos)
    if path == "direct":  # footprint-size square of network pixels around the rounded centre
        (r0, r1), (c0, c1) = (_box(v, sim.footprint_size(sim.coarse) // 2) for v in pos)
    else:  # footprint-size square of sensor pixels around the rounded fine centre, mapped to network pixels
        (r0, r1), (c0, c1) = (_box(_fine(v), sim.footprint_size(sim.fine) // 2) for v in pos)
        r0, r1, c0, c1 = (math.floor(v / K) for v in (r0, r1, c0, c1))
    r0, c0, r1, c1 = max(r0, 0), max(c0, 0), min(r1, N - 1), min(c1, N - 1)
    if r0 <= r1 and c0 <= c1:
        mask[r0:r1 + 1, c0:c1 + 1] = True
    return mask


def _is_rounding_tie(v: float, on_axis: bool) -> bool:
    """A centre within 1e-3 px of a half pixel: float32 and float64 angles may then round to different footprint
    boxes (test_half_pixel_laser_position_moves_only_the_footprint_margin). An on-axis coordinate is exact."""
    return not on_axis and abs((v - math.floor(v)) - 0.5) < 1e-3


AWAY_TOL_DN = 1.0  # |float32 - float64| counts away from the laser's footprint (benchmarks/bench_accuracy.py)


def _simulate_sweep(path: str, pos, alphas: list[float]):
    """(float64 simulator, {dtype: outputs}, the network pixels away from the footprint): one batch per precision,
    one sample per laser strength, same scene, seed and noise draws."""
    sims = {dt: U.make_sim(U.ODD, R, N, path=path) for dt in (torch.float32, torch.float64)}
    sim = sims[torch.float64]
    angle = 0.0 if pos is None else U.laser_angle(sim, *pos)
    scene64 = U.random_scene(sim, batch=len(alphas), seed=4)
    outs = {}
    for dt in (torch.float32, torch.float64):
        coded, _, _ = U.states(U.ODD, dt)
        p = U.params(len(alphas), dtype=dt, alpha_b=0.6, laser_angle_rad=angle, **U.NOISY).replace(
            alpha_l=torch.tensor(alphas, dtype=dt))
        outs[dt] = sims[dt](scene64.to(dt), p, coded, seed=11)
    return sim, outs, ~_footprint(sim, pos, path)


def _dn_difference(outs: dict, i: int) -> torch.Tensor:
    """|float32 - float64| counts of sample i, as an (N, N) float64 map."""
    return (outs[torch.float32]["sensor_dn"][i, 0].double() - outs[torch.float64]["sensor_dn"][i, 0]).abs()


def float32_away_error(path: str, where: str, alphas: list[float] = ALPHAS) -> float:
    """Largest |float32 - float64| counts away from the footprint over the strengths ``alphas``, the laser at
    POSITIONS[where] (RANDOM_POSITIONS[where] if not there)."""
    pos = POSITIONS.get(where, RANDOM_POSITIONS.get(where))
    _, outs, away = _simulate_sweep(path, pos, alphas)
    return max(float(_dn_difference(outs, i)[away].max()) for i in range(len(alphas)))


def _check_sweep(path: str, pos, alphas: list[float]) -> dict:
    c = _centre(pos)
    for v in c:  # the grid avoids footprint-rounding ties on both levels (the tie has its own test)
        on_axis = v == (N - 1) / 2
        assert not _is_rounding_tie(v, on_axis) and not _is_rounding_tie(_fine(v), on_axis), f"{pos} is a tie"
    sim, outs, away = _simulate_sweep(path, pos, alphas)
    for dt in (torch.float32, torch.float64):
        _finite(outs[dt])
        assert outs[dt]["sensor_dn"].dtype == dt
    o32, o64 = outs[torch.float32], outs[torch.float64]
    fw, s_sat, sq = U.full_well_dn(sim), sim.sensor.saturation_dn, U.quant_std(sim)
    assert int(away.sum()) > N * N // 3
    inside_field = bool((~away).any())
    worst = {"away": 0.0, "inside": 0.0}
    for i, a in enumerate(alphas):
        for o in (o32, o64):
            dn, sat = o["sensor_dn"][i, 0].double(), o["saturated"][i, 0]
            assert float(dn.min()) >= 0.0 and float(dn.max()) <= s_sat
            if path == "direct":
                # e >= e_sat is clamped to e_sat and gets no quantization noise: saturated <=> exactly G e_sat
                assert torch.equal(sat, dn == fw), f"alpha_l={a:g}: saturated mask and counts disagree"
            else:
                # a network pixel is saturated when >= half of its K x K sensor pixels are; those read exactly
                # G e_sat, the others at most G e_sat (e < e_sat, dithered rounding), so none reads above it
                need = math.ceil(K * K / 2) / (K * K) * fw
                assert -_max(-dn[sat], -fw) >= need - 1e-3, f"alpha_l={a:g}"
                assert float(dn.max()) <= fw
            # no laser light outside the footprint, in either precision
            assert torch.equal(o["laser"][i, 0][away], torch.zeros_like(o["laser"][i, 0][away]))
        d = _dn_difference(outs, i)
        worst["away"] = max(worst["away"], float(d[away].max()))
        worst["inside"] = max(worst["inside"], _max(d[~away]))
        assert float(d[away].max()) <= AWAY_TOL_DN, f"alpha_l={a:g}: float32 differs by {float(d[away].max()):.3g} DN"
        sat32, sat64 = o32["saturated"][i, 0], o64["saturated"][i, 0]
        assert torch.equal(sat32[away], sat64[away]), f"alpha_l={a:g}"
        # inside the footprint the masks may differ only at threshold ties: a pixel saturated in one precision and
        # not in the other sits within rounding of full well, so its two counts are within the quantization noise
        tie = sat32 != sat64
        assert _max(d[tie]) <= 1.0 + 5 * sq, f"alpha_l={a:g}: a mask mismatch is not a tie"
        assert int(tie.sum()) <= N * N // 100
        # the laser irradiance itself: placed in float64 from each precision's own PSF, so the float32 map carries
        # only the float32 optics' PSF error (measured 1.4e-5 of the peak)
        l32, l64 = o32["laser"][i, 0].double(), o64["laser"][i, 0]
        assert float((l32 - l64).abs().max()) <= 1e-4 * float(l64.max())
        if a > 0 and inside_field:
            assert float(o64["laser"][i, 0].max()) > 0  # the laser does land inside the footprint
        if a == 0 or not inside_field:
            assert float(o64["laser"][i, 0].abs().max()) == 0.0
    if inside_field and alphas[-1] >= 1e6:
        # the strongest lasers saturate their core in both precisions, with the same mask
        assert bool(o32["saturated"][-1].any()) and bool(o64["saturated"][-1].any())
        core = o64["laser"][-1, 0] > 2.0
        assert bool(core.any()) and torch.equal(o32["saturated"][-1, 0][core], o64["saturated"][-1, 0][core])
    return worst


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("where", list(POSITIONS))
def test_float32_laser_sweep_matches_float64(path, where):
    _check_sweep(path, POSITIONS[where], ALPHAS)


@pytest.mark.slow
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("where", list(POSITIONS) + list(RANDOM_POSITIONS))
def test_float32_laser_sweep_every_decade(path, where):
    pos = POSITIONS.get(where, RANDOM_POSITIONS.get(where))
    _check_sweep(path, pos, ALPHAS_EVERY_DECADE)


@pytest.mark.parametrize("path", PATHS)
def test_half_pixel_laser_position_moves_only_the_footprint_margin(path):
    """A known limit of the laser model, pinned by bounds. The footprint is a fixed-size box around the *rounded*
    laser centre, and the window PSF's Fourier interpolant rings slightly beyond the window; so as the centre
    crosses a half pixel, the box gains a column of ringing on one side and loses one on the other. The laser map
    jumps there (by < 0.1 % of its energy, all in that margin column), and a float32 angle, rounded differently,
    can land on the other side of the tie than its float64 reference: at alpha_l = 1e8 the margin column then
    saturates in one precision only. Everything outside the margin column stays within round-off."""
    sims = {dt: U.make_sim(U.ODD, R, N, path=path) for dt in (torch.float32, torch.float64)}
    sim = sims[torch.float64]
    row, col = 10.5, 3.5  # row on the axis (exact); col a half-pixel tie on both levels
    assert _is_rounding_tie(col, False) and _is_rounding_tie(_fine(col), False)
    coded64, _, _ = U.states(U.ODD, torch.float64)
    eps = 1e-7
    maps = []
    for c in (col - eps, col + eps):
        p = U.params(alpha_l=1.0, laser_angle_rad=U.laser_angle(sim, row, c))
        maps.append(sim(U.uniform_scene(sim, 0.0), p, coded64, seed=0)["laser"][0, 0])
    below, above = (_footprint(sim, (row, c), path) for c in (col - eps, col + eps))
    # the columns (of the simulated level's pixels) that only one of the two boxes covers, as network columns
    level = sim.coarse if path == "direct" else sim.fine
    half, centre = sim.footprint_size(level) // 2, col if path == "direct" else _fine(col)
    cols_below, cols_above = (set(range(_box(c, half)[0], _box(c, half)[1] + 1)) for c in (centre - eps,
                                                                                             centre + eps))
    flipped = {c if path == "direct" else math.floor(c / K) for c in cols_below ^ cols_above}
    flipped = sorted(c for c in flipped if 0 <= c < N)
    assert len(flipped) == 1  # one column on the sensor (the other flipped column is off its left edge)
    margin = (below | above) & (torch.arange(N) == flipped[0])[None, :]
    jump = (maps[0] - maps[1]).abs()
    total = float(maps[1].sum())
    assert float(jump[~margin].max()) <= 1e-3 * float(maps[1].max())  # measured 2e-4: energy renormalization
    assert float(jump[margin].sum()) <= 2e-3 * total  # measured 7.6e-4 of the laser's energy
    # float32 against float64 at the tie itself
    outs = {}
    for dt in (torch.float32, torch.float64):
        coded, _, _ = U.states(U.ODD, dt)
        p = U.params(1, dtype=dt, alpha_b=0.6, alpha_l=1e8, laser_angle_rad=U.laser_angle(sim, row, col), **U.NOISY)
        outs[dt] = sims[dt](U.random_scene(sim, seed=4).to(dt), p, coded, seed=11)
        _finite(outs[dt])
    o32, o64 = outs[torch.float32], outs[torch.float64]
    d = (o32["sensor_dn"][0, 0].double() - o64["sensor_dn"][0, 0]).abs()
    either = below | above
    assert float(d[~either].max()) <= 1.0
    assert torch.equal(o32["saturated"][0, 0][~margin], o64["saturated"][0, 0][~margin])
