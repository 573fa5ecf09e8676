"""Random phase masks through phase -> PSF -> LSR (smooth and sampled) / MTF, and the gradients back to the mask.

1000 half-ring masks (1-8 rings, r log-uniform over [0.5, 200] in units of lambda f / W_a plus the bounds exactly,
theta over [0, 2 pi] plus 0 and 2 pi exactly, both conventions, both harmonic signs, several order ranges and all
three evaluation strategies), a tenth of them placed on a zero crossing of Q0 = sum_n r_n J_0(x_n), the
denominator of atan / atan2, at a sample of the pupil grid. Half of those have every theta_n = 0, so that on the
+v axis Im = 0 exactly as well: atan2(0, ~0), the worst case of the phase. Plus random freeform phases
(PixelPhaseMask). Everything must be finite, and what physics bounds must hold: a phase-only mask cannot raise the
peak above the uncoded one (LSR <= 1), the smooth LSR bounds the sampled one from above, the window holds at most
all the energy, and the MTF is 1 at DC and at most 1. A float64 gradcheck on a sample of masks, a near-zero-crossing
one included, checks the gradients' values. The published mask's gradchecks are in tests/optics/test_halfring.py.
"""
from __future__ import annotations

import math

import pytest
import torch

from codesign.optics import HalfRingMask, OpticalSystem, OpticsSpec, PixelPhaseMask, RadialMTF, bessel_j
from codesign.optics.metrics import lsr_sampled, lsr_smooth, mtf

R_LO, R_HI = 0.5, 200.0
BAND = (0.0, 0.5)


# ---- mask parameters ------------------------------------------------------------------------------------------
def _random_masks(count: int, seed: int) -> list[dict]:
    """Keyword arguments of ``count`` random HalfRingMasks (deterministic for a seed)."""
    g = torch.Generator().manual_seed(seed)
    u = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    out = []
    for i in range(count):
        n = int(torch.randint(1, 9, (1,), generator=g))
        r = torch.exp(math.log(R_LO) + (math.log(R_HI) - math.log(R_LO)) * u(n))
        theta = 2 * math.pi * u(n)
        if i % 20 == 0:  # the bounds exactly
            r[0], theta[0] = R_LO, 0.0
            r[-1], theta[-1] = R_HI, 2 * math.pi
        m_range = [(1, 17), (1, 17), (1, 17), (0, 17), (5, 5), (0, 30)][i % 6]
        strategy = "exact" if i % 10 else ["table", "direct"][(i // 10) % 2]
        out.append(dict(r=r.tolist(), theta=theta.tolist(), convention=("atan2", "atan")[i % 2],
                        harmonic_sign=("printed", "fourier")[(i // 2) % 2], m_range=m_range, strategy=strategy,
                        table_size=512))
    return out


def _on_q0_zero_crossings(masks: list[dict], grid, aperture: float, seed: int) -> list[dict]:
    """Move ring 0 of each mask onto the first root r_0 in [0.5, 200] of Q0(xi) = 0 at a grid radius xi (one of the
    +v-axis radii when every theta is 0, so that Im = 0 there too). A scan for a sign change, then bisection to the
    last bit, all masks at once, with the library's J_0 (bessel_j(x, 1): the mask's bessel_j(x, n_max) may differ in
    the last bits, so Q0 vanishes to ~1e-16 of sum r_n, checked below) and the mask's argument x = (2 pi / W_a) r xi.
    Masks whose radius has no root in the range for their other rings are dropped."""
    g = torch.Generator().manual_seed(seed)
    radii = grid.radii.to(torch.float64)
    k = radii / grid.pitch
    axis = torch.nonzero((k - torch.round(k)).abs() < 1e-9).squeeze(-1)[1:]  # (0, j) samples: radius j * pitch
    c = 2 * math.pi / aperture
    xi, rest = [], []
    for m in masks:
        pool = axis if all(t == 0.0 for t in m["theta"]) else torch.arange(1, radii.numel())
        x = radii[pool[int(torch.randint(0, pool.numel(), (1,), generator=g))]]
        r = torch.tensor(m["r"][1:], dtype=torch.float64)
        xi.append(x)
        rest.append((r * bessel_j((c * r) * x, 1)[..., 0]).sum())  # the other rings' share of Q0(xi)
    xi, rest = torch.stack(xi), torch.stack(rest)

    def q0(r0: torch.Tensor) -> torch.Tensor:  # r0: (B,) or (B, C)
        x, s = (xi, rest) if r0.dim() == 1 else (xi[:, None], rest[:, None])
        return r0 * bessel_j((c * r0) * x, 1)[..., 0] + s

    cand = torch.exp(torch.linspace(math.log(R_LO), math.log(R_HI), 2000, dtype=torch.float64))
    v = q0(cand.expand(len(masks), -1).contiguous())
    change = v[:, :-1] * v[:, 1:] <= 0
    found = change.any(1)
    first = change.to(torch.int64).argmax(1)
    lo, hi = cand[first], cand[first + 1]
    f_lo = q0(lo)
    for _ in range(80):  # halves [lo, hi] down to adjacent floats
        mid = (lo + hi) / 2
        f_mid = q0(mid)
        left = f_mid * f_lo <= 0
        hi, lo, f_lo = torch.where(left, mid, hi), torch.where(left, lo, mid), torch.where(left, f_lo, f_mid)
    root = torch.where(q0(lo).abs() <= q0(hi).abs(), lo, hi)
    out = []
    for i, m in enumerate(masks):
        if bool(found[i]):
            out.append({**m, "r": [float(root[i])] + list(m["r"][1:]), "xi": float(xi[i])})
    return out


def _exact_zero_masks(count: int, grid, aperture: float, seed: int) -> list[dict]:
    """Two-ring float64 masks, every theta 0, orders m_o = 3..35, where Q0 is exactly 0.0 at a +v-axis sample of
    the grid, where Im is exactly 0 too: the phase there is atan2(0, 0) (atan: atan of 0 / 0). Ring 0 is put on
    the root as above, then stepped ulp by ulp (up to 400 each way) until the library's own arithmetic,
    r_0 J_0(x_0) + r_1 J_0(x_1) with x = ((2 pi / W_a) r) xi and J from bessel_j(x, 35), cancels exactly."""
    g = torch.Generator().manual_seed(seed)
    base = [dict(r=[1.0, float(3.0 + 97.0 * torch.rand(1, generator=g, dtype=torch.float64))], theta=[0.0, 0.0],
                 convention=("atan2", "atan")[i % 2], harmonic_sign="printed", m_range=(1, 17), strategy="exact",
                 table_size=512) for i in range(12 * count)]
    c = 2 * math.pi / aperture
    out = []
    for m in _on_q0_zero_crossings(base, grid, aperture, seed + 1):
        r0, r1 = (torch.tensor(v, dtype=torch.float64) for v in m["r"])
        xi = torch.tensor(m["xi"], dtype=torch.float64)
        ulp = torch.nextafter(r0, torch.tensor(math.inf, dtype=torch.float64)) - r0
        cand = r0 + torch.arange(-400, 401, dtype=torch.float64) * ulp  # exact: r0 is far from a power of 2
        q0 = cand * bessel_j((c * cand) * xi, 35)[..., 0] + r1 * bessel_j((c * r1) * xi, 35)[..., 0]
        hit = torch.nonzero(q0 == 0.0).squeeze(-1)
        if hit.numel():
            out.append({**m, "r": [float(cand[hit[0]]), float(r1)]})
        if len(out) == count:
            return out
    raise AssertionError(f"only {len(out)} masks with an exact zero of Q0 found")


def _zero_crossing_masks(count: int, grid, aperture: float, seed: int) -> list[dict]:
    base = _random_masks(3 * count, seed)
    for i, m in enumerate(base):
        m["strategy"] = "exact"  # the root sits on a grid radius: the exact strategy evaluates Q0 at that very value
        if i % 2 == 0:
            m["theta"] = [0.0] * len(m["theta"])
            m["convention"] = ("atan2", "atan")[(i // 2) % 2]
    masks = _on_q0_zero_crossings(base, grid, aperture, seed + 1)
    assert len(masks) >= count
    return masks[:count]


# ---- the forward / backward sweep ----------------------------------------------------------------------------
def _sweep(system: OpticalSystem, masks: list, radial: RadialMTF) -> dict:
    """Phase, PSF, LSRs and MTF of every mask (batched from the PSF on), gradients of the summed smooth LSR and of
    the summed mtf_mean w.r.t. every mask parameter; asserts finiteness and the physical bounds."""
    eps = 1e-5 if system.dtype == torch.float32 else 1e-12
    phases = torch.stack([m.phase() for m in masks])
    ph = phases.detach()
    assert bool(torch.isfinite(ph).all()), "non-finite phase"
    for m, p in zip(masks, ph):
        if isinstance(m, HalfRingMask):
            bound = math.pi if m.convention == "atan2" else math.pi / 2
            assert float(p.abs().max()) <= bound + eps
    psf = system.psf(phases)
    h = psf.detach()
    assert bool(torch.isfinite(h).all()) and float(h.min()) >= 0
    assert float(h.sum(dim=(-2, -1)).max()) <= 1 + eps  # the window holds at most all the energy
    sampled = lsr_sampled(h, system.uncoded_peak)
    smooth = lsr_smooth(psf, system.uncoded_peak, 16.0)
    assert bool(torch.isfinite(sampled).all()) and bool(torch.isfinite(smooth.detach()).all())
    # |sum A exp(i phi) ...| <= sum A: no phase-only mask beats the uncoded on-axis peak
    assert float(sampled.max()) <= 1 + 10 * eps
    assert bool((smooth.detach() >= sampled * (1 - 10 * eps)).all())  # ||h||_16 >= max h
    m2 = mtf(psf)
    m2d = m2.detach()
    assert bool(torch.isfinite(m2d).all())
    torch.testing.assert_close(m2d[..., 0, 0], torch.ones_like(m2d[..., 0, 0]), rtol=0, atol=10 * eps)
    assert float(m2d.max()) <= 1 + 10 * eps
    radial_mtf = radial(m2)
    mtf_mean, _ = radial.summary(radial_mtf, BAND)
    mm = mtf_mean.detach()
    assert bool(torch.isfinite(radial_mtf.detach()).all()) and bool(((mm > 0) & (mm <= 1 + 10 * eps)).all())
    params = [p for m in masks for p in m.parameters()]
    g_lsr = torch.autograd.grad(smooth.sum(), params, retain_graph=True)
    g_mtf = torch.autograd.grad(mtf_mean.sum(), params)
    for name, grads in (("lsr_smooth", g_lsr), ("mtf_mean", g_mtf)):
        bad = [i for i, gr in enumerate(grads) if not bool(torch.isfinite(gr).all())]
        assert not bad, f"non-finite d {name} / d parameters for {len(bad)} masks, first {bad[0]}"
    # the gradients carry signal: all but a handful of masks move their smooth LSR
    moving = sum(float(gr.abs().sum()) > 0 for gr in g_lsr)
    assert moving >= 0.95 * len(params)
    return {"lsr": sampled, "g_lsr": g_lsr, "g_mtf": g_mtf}


def _halfrings(system: OpticalSystem, specs: list[dict], aperture: float) -> list[HalfRingMask]:
    keep = ("r", "theta", "convention", "harmonic_sign", "m_range", "strategy", "table_size")
    return [HalfRingMask(system.grid, aperture, **{k: s[k] for k in keep}) for s in specs]


def _halfring_sweep(spec: OpticsSpec, dtype, count: int, seed: int):
    system = OpticalSystem(spec, dtype=dtype)
    a = spec.aperture_diameter_m
    zc = _zero_crossing_masks(count // 10, OpticalSystem(spec, dtype=torch.float64).grid, a, seed + 100)
    specs = _random_masks(count - len(zc), seed) + zc
    assert len(specs) == count
    out = _sweep(system, _halfrings(system, specs, a), RadialMTF(spec))
    return specs, zc, out


def test_1000_random_half_ring_masks_float32(tiny_spec):
    specs, zc, out = _halfring_sweep(tiny_spec, torch.float32, 1000, seed=0)
    assert len(zc) == 100 and sum(all(t == 0.0 for t in s["theta"]) for s in zc) >= 40
    # the sweep reaches the physical extremes: nearly uncoded masks (small r: LSR near 1) and strongly spreading ones
    lsr = out["lsr"]
    assert float(lsr.max()) > 0.5 and float(lsr.min()) < 0.05


def test_zero_crossing_masks_really_sit_on_a_zero_of_q0(tiny_system64, tiny_spec):
    """The construction above is what the sweep relies on: Q0 at the chosen grid radius is zero to the last bits
    (relative to sum r_n, the scale of Q0), and on the +v axis of an all-theta-0 mask Im is exactly zero there."""
    a = tiny_spec.aperture_diameter_m
    grid = tiny_system64.grid
    exact = _exact_zero_masks(4, grid, a, seed=400)
    zc = _zero_crossing_masks(40, grid, a, seed=100) + exact
    for s in zc:
        m = HalfRingMask(grid, a, s["r"], s["theta"], convention=s["convention"], harmonic_sign=s["harmonic_sign"],
                         m_range=s["m_range"])
        with torch.no_grad():
            q0, im = m.field_parts()
        at = (grid.radii.to(torch.float64)[grid.radius_index] - s["xi"]).abs() < 1e-15
        assert bool(at.any())
        assert float(q0[at].abs().max()) <= 1e-13 * sum(s["r"]), f"Q0 = {float(q0[at].abs().max()):.3g}"
        if all(t == 0.0 for t in s["theta"]):  # the sample(s) on the +v axis: angle exactly 0
            on_axis = at & (grid.angle.reshape(-1)[grid.support] == 0)
            assert bool(on_axis.any()) and float(im[on_axis].abs().max()) == 0.0
    for s in exact:  # and these are the exact 0 / 0
        m = HalfRingMask(grid, a, s["r"], s["theta"], convention=s["convention"])
        with torch.no_grad():
            q0, im = m.field_parts()
        both = (q0 == 0) & (im == 0)
        assert bool(both.any()), "no sample with Q0 = Im = 0 exactly"
        assert float(m.phase().detach().reshape(-1)[grid.support][both].abs().max()) == 0.0
    # and in float64 the sweep's forward/backward are finite for all of them
    system = tiny_system64
    masks = _halfrings(system, zc, a)
    out = _sweep(system, masks, RadialMTF(tiny_spec))
    # the atan2(0, ~0) masks: d phase / d theta = (d Im / d theta) / Q0 is huge but finite
    big = max(float(g.abs().max()) for g in out["g_lsr"])
    assert math.isfinite(big) and big > 1e6


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_random_freeform_phases(tiny_spec, dtype):
    """PixelPhaseMask: uniform phases, huge ones (1e3 and 1e6 rad: float32 keeps only the fractional turns it
    can), zero, constant pi, a +-pi/2 checkerboard (moves the light half a replica period off the axis), and tilts
    up to one half cycle per sample."""
    system = OpticalSystem(tiny_spec, dtype=dtype)
    grid = system.grid
    g = torch.Generator().manual_seed(3)
    n = grid.n
    ii, jj = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    phases = [torch.zeros(n, n), torch.full((n, n), math.pi), (math.pi / 2) * (1 - 2 * ((ii + jj) % 2)).double()]
    phases += [(2 * math.pi * k / n) * ii.double() for k in (1, 7, n // 2)]  # tilts up to the Nyquist rate
    for i in range(150):
        amp = [math.pi, 1e3, 1e6][i % 3]
        phases.append(amp * (2 * torch.rand(n, n, generator=g, dtype=torch.float64) - 1))
    masks = [PixelPhaseMask(grid, p.to(dtype)) for p in phases]
    out = _sweep(system, masks, RadialMTF(tiny_spec))
    # a constant phase is the uncoded pupil: LSR 1
    for k in (0, 1):
        assert float(out["lsr"][k]) == pytest.approx(1.0, abs=1e-5)


# ---- gradcheck on a sample -------------------------------------------------------------------------------------
def _gradcheck_masks(grid, aperture: float) -> list[dict]:
    """Three random masks of up to 3 rings (atan / printed, atan2 / fourier, atan / fourier with m_o = 1) and a
    3-ring atan2 mask on a zero crossing of Q0 off the theta rays (Im != 0 there, so atan2 is smooth through
    Q0 = 0). Not an atan mask on a crossing: atan jumps by pi where Q0 changes sign, a true discontinuity that no
    finite difference can straddle."""
    small = lambda m, **kw: {**m, "r": m["r"][:3], "theta": m["theta"][:3], "strategy": "exact", **kw}  # noqa: E731
    sample = [small(m) for m in _random_masks(4, seed=11)[1:]]
    zc = _on_q0_zero_crossings([small(m, convention="atan2") for m in _random_masks(8, seed=12)[1:]], grid,
                               aperture, seed=13)
    assert zc
    return sample + zc[:1]


def test_gradcheck_phase_psf_lsr_smooth_and_mtf_on_a_sample(tiny_system64, tiny_spec):
    system, a = tiny_system64, tiny_spec.aperture_diameter_m
    radial = RadialMTF(tiny_spec)
    band = radial.band_mask(BAND)
    for s in _gradcheck_masks(system.grid, a):
        mask = HalfRingMask(system.grid, a, s["r"], s["theta"], convention=s["convention"],
                            harmonic_sign=s["harmonic_sign"], m_range=s["m_range"])
        with torch.no_grad():
            q0, im = mask.field_parts()
        rel = float(q0.abs().min()) / sum(s["r"])
        if "xi" in s:
            assert rel <= 1e-13  # really on the crossing, and Im != 0 there: atan2 is smooth through it
            at = (system.grid.radii[system.grid.radius_index] - s["xi"]).abs() < 1e-15
            assert float(im[at].abs().min()) >= 1e-6 * sum(s["r"])
        elif s["convention"] == "atan":
            assert rel >= 1e-4  # far from one: a step of 1e-6 in r cannot cross it

        def chain(r, theta, mask=mask):
            psf = system.psf(torch.func.functional_call(mask, {"r": r, "theta": theta}, ()))
            return lsr_smooth(psf, system.uncoded_peak, 16.0), radial(mtf(psf))[band]

        inputs = (torch.tensor(s["r"], dtype=torch.float64, requires_grad=True),
                  torch.tensor(s["theta"], dtype=torch.float64, requires_grad=True))
        assert torch.autograd.gradcheck(chain, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


# ---- the slow level ---------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_2000_random_half_ring_masks_on_the_small_spec_float32(small_spec):
    _halfring_sweep(small_spec, torch.float32, 2000, seed=1)


@pytest.mark.slow
def test_1000_random_half_ring_masks_float64(tiny_spec):
    _halfring_sweep(tiny_spec, torch.float64, 1000, seed=2)


@pytest.mark.slow
def test_many_masks_with_an_exact_zero_over_zero_phase(tiny_system64, tiny_spec):
    a = tiny_spec.aperture_diameter_m
    masks = _halfrings(tiny_system64, _exact_zero_masks(40, tiny_system64.grid, a, seed=500), a)
    _sweep(tiny_system64, masks, RadialMTF(tiny_spec))
