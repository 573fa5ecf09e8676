"""Accuracy: the largest errors of the checks the tests make, measured next to the tolerances they assert.

Each row repeats one test's comparison (closed form, scipy, float64 reference, the other propagator, finite
differences, noise moments against their closed forms, an uninterrupted run) on the test's setup and reports
the largest error found; "of tol" = measured / tolerance (below 1: the test passes with that much room).
Finite-difference rows use the test's eps and report max |analytic - numerical| / (atol + rtol |numerical|)
over the whole Jacobian. Noise rows report the largest |z| = |estimate - closed form| / standard error.
docs/accuracy.md quotes these numbers.

    python -m benchmarks.bench_accuracy --scale quick
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch
from scipy import special

from benchmarks.common import Report, markdown_table, write_json

F64, F32, CPU = torch.float64, torch.float32, torch.device("cpu")
W_A = 3.83e-3


def _row(area, check, test, reference, tol, measured, tol_text=None) -> dict:
    return {"area": area, "check": check, "test": test, "reference": reference, "tolerance": tol_text or f"{tol:.2g}",
            "tol": float(tol), "measured": float(measured), "of_tol": float(measured) / tol if tol else None}


def _jacobian_error(fn, inputs, eps: float, atol: float, rtol: float) -> float:
    """max over Jacobian entries of |analytic - central difference| / (atol + rtol |central difference|)."""
    def flat(*xs):
        out = fn(*xs)
        return torch.cat([o.reshape(-1) for o in (out if isinstance(out, tuple) else (out,))])

    inputs = [x.detach() for x in inputs]
    analytic = torch.autograd.functional.jacobian(flat, tuple(inputs))
    worst = 0.0
    for i, x in enumerate(inputs):
        a = analytic[i].reshape(analytic[i].shape[0], -1)
        for j in range(x.numel()):
            shifted = []
            for sign in (1, -1):
                xs = [t.clone() for t in inputs]
                xs[i].view(-1)[j] += sign * eps
                shifted.append(flat(*xs).detach())
            num = (shifted[0] - shifted[1]) / (2 * eps)
            worst = max(worst, float(((a[:, j] - num).abs() / (atol + rtol * num.abs())).max()))
    return worst


# ---- optics -------------------------------------------------------------------------------------------------
def _native_spec(focal_n, fft_n=192, samples=64):
    from codesign.optics import OpticsSpec

    base = OpticsSpec.with_samples_across(samples, focal_n=16)
    pitch = base.lambda_f / (fft_n * base.pupil_pitch_m)
    return OpticsSpec.with_samples_across(samples, focal_n=focal_n, focal_pitch_m=pitch, fft_n=fft_n)


def _phases(system):
    from codesign.optics.masks import published_halfring

    n, g = system.grid.n, torch.Generator().manual_seed(1234)
    rand = ((torch.rand(n, n, generator=g, dtype=F64) * 2 - 1) * 5 * math.pi).to(system.dtype)
    return [torch.zeros(n, n, dtype=system.dtype), rand,
            published_halfring(system.grid, system.spec.aperture_diameter_m).phase().detach()]


def optics_rows(scale: str) -> list[dict]:
    from codesign.optics import OpticalSystem, OpticsSpec, RadialMTF, airy_psf, circular_mtf, metrics
    from codesign.optics.bessel import bessel_j
    from codesign.optics.grid import axis_coords
    from codesign.optics.masks import PUBLISHED_R, PUBLISHED_THETA, HalfRingMask

    A, rows = "optics", []
    tb = "tests/optics/test_bessel.py::"
    # Bessel J_0..J_60 on the tests' grid: uniform over [0, 1000], log-spaced from 1e-6, dense below 80 (turning
    # points x ~ n) and around the algorithm's switch points 1, 25, 62
    x = [np.linspace(0, 1000, 4001 if scale == "quick" else 40001), np.geomspace(1e-6, 1000, 400),
         np.linspace(0, 80, 1601), [0.0, 1e-300, 1e-12, 1e-8]]
    x += [s + np.linspace(-w, w, k) for s in (1.0, 25.0, 62.0) for w, k in ((2.0, 81), (1e-3, 41))]
    x = np.unique(np.clip(np.concatenate([np.asarray(v, dtype=np.float64) for v in x]), 0, 1000))
    orders = np.arange(61)
    for dtype, tol in ((F64, 1e-10), (F32, 1e-5)):
        xt = torch.from_numpy(x).to(dtype)
        ref = special.jv(orders[None, :], xt.double().numpy()[:, None])  # at the rounded arguments
        err = np.abs(bessel_j(xt, 60).double().numpy() - ref).max()
        name = "float64" if dtype == F64 else "float32"
        rows.append(_row(A, f"J_n, n <= 60, x in [0, 1000], {name}", tb + f"test_bessel_{name}_matches_scipy_to_"
                         + ("1e10" if dtype == F64 else "1e5"), "scipy.special.jv", tol, err))
        xg = xt[::7].clone().requires_grad_(True)
        j = bessel_j(xg, 60)
        xd = xg.detach().double().numpy()
        d_ref = 0.5 * (special.jv(orders[None, :] - 1, xd[:, None]) - special.jv(orders[None, :] + 1, xd[:, None]))
        d_ref[:, 0] = -special.jv(1, xd)
        gerr = max(float(np.abs(torch.autograd.grad(j[:, n].sum(), xg, retain_graph=True)[0].double().numpy()
                                - d_ref[:, n]).max()) for n in orders)
        rows.append(_row(A, f"dJ_n/dx, {name}", tb + "test_bessel_gradient_matches_recurrence_derivative",
                         "(J_{n-1} - J_{n+1}) / 2 with scipy", tol, gerr))
    worst = max(_jacobian_error(lambda t: bessel_j(t, 60), [torch.tensor([x0, 0.97 * x0], dtype=F64)], 1e-6, 1e-7,
                                1e-6) for x0 in (0.3, 0.9, 3.7, 24.0, 30.5, 61.0, 70.0, 640.0))
    rows.append(_row(A, "J_n gradient at 8 points, float64", tb + "test_bessel_gradcheck_float64",
                     "central differences, eps 1e-6", 1.0, worst, "atol 1e-7 + rtol 1e-6"))

    tp = "tests/optics/test_psf.py::"
    spec = OpticsSpec.with_samples_across(64, focal_n=64)
    sys64 = OpticalSystem(spec, dtype=F64)
    airy0 = float(airy_psf(torch.zeros(1, dtype=F64), spec))
    rows.append(_row(A, "uncoded peak h0(0)", tp + "test_uncoded_peak_matches_airy_peak", "Airy peak pi W_a^2 dx^2 / "
                     "(4 (lambda f)^2)", 1e-2, abs(sys64.uncoded_peak / airy0 - 1), "1e-02 rel"))
    c = axis_coords(spec.focal_n, spec.focal_pitch_m, dtype=F64)
    airy = airy_psf(torch.sqrt(c[:, None] ** 2 + c[None, :] ** 2), spec)
    rows.append(_row(A, "uncoded PSF, 64 x 64 window", tp + "test_uncoded_psf_matches_airy_pattern",
                     "Airy pattern (hard edge)", 1e-2, float((sys64.uncoded_psf() - airy).abs().max() / airy.max()),
                     "1e-02 of peak"))
    per = 40
    fine = OpticsSpec.with_samples_across(64, focal_n=128, focal_pitch_m=spec.lambda_f_over_d / per)
    line = OpticalSystem(fine, dtype=F64, method="mft").uncoded_psf()[64, 64:]
    i = int(torch.argmin(line[: 2 * per]))
    y0, y1, y2 = (float(line[i + k]) for k in (-1, 0, 1))
    zero = (i + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)) / per
    rows.append(_row(A, "first dark ring of the uncoded PSF", tp + "test_uncoded_first_zero_at_1p22_lambda_f_over_d",
                     "1.2197 lambda f / W_a", 1e-2, abs(zero / 1.2197 - 1), "1e-02 rel"))
    nat = _native_spec(192, 192)
    for dtype, tol in ((F64, 1e-10), (F32, 1e-5)):
        s = OpticalSystem(nat, dtype=dtype, method="fft")
        err = max(abs(float(s.psf(p).double().sum()) - 1) for p in _phases(s))
        name = "float64" if dtype == F64 else "float32"
        rows.append(_row(A, f"energy of the whole plane (FFT, native pitch), {name}",
                         tp + "test_fft_native_pitch_whole_plane_sums_to_one", "Parseval: 1", tol, err))
    s = OpticalSystem(nat, dtype=F64, method="mft")
    rows.append(_row(A, "energy of one replica period (MFT)", tp + "test_mft_whole_period_sums_to_one", "Parseval: 1",
                     1e-10, max(abs(float(s.psf(p).sum()) - 1) for p in _phases(s))))
    same = _native_spec(64, 192)
    for dtype, tol in ((F64, 1e-6), (F32, 1e-4)):
        mft, fft = (OpticalSystem(same, dtype=dtype, method=m) for m in ("mft", "fft"))
        phases = _phases(mft) if dtype == F64 else _phases(mft)[2:]
        err = max(float((mft.psf(p) - fft.psf(p)).abs().max() / mft.psf(p).max()) for p in phases)
        rows.append(_row(A, f"MFT vs FFT on the same window, {'float64' if dtype == F64 else 'float32'}",
                         tp + ("test_mft_equals_fft_on_the_same_window" if dtype == F64 else
                               "test_mft_equals_fft_in_float32"), "the other propagator", tol, err,
                         f"{tol:.0e} of peak"))
    res = OpticsSpec.with_samples_across(64, focal_n=64, fft_n=560)
    mft, fft = (OpticalSystem(res, dtype=F64, method=m) for m in ("mft", "fft"))
    err = max(float((mft.psf(p) - fft.psf(p)).abs().max() / mft.psf(p).max()) for p in _phases(mft)[::2])
    rows.append(_row(A, "FFT resampled to the sensor pitch vs MFT", tp + "test_fft_resampled_onto_sensor_pitch_"
                     "approximates_mft", "MFT (exact)", 0.03, err, "3e-02 of peak"))
    m128 = OpticalSystem(_native_spec(128, 128, 48), dtype=F64, method="mft")
    a = m128.grid.aperture
    pad = torch.zeros(128, 128, dtype=F64)
    pad[: a.shape[0], : a.shape[1]] = a
    ac = torch.fft.ifft2(torch.fft.fft2(pad).abs() ** 2).real
    rows.append(_row(A, "uncoded MTF (window = one period)", tp + "test_uncoded_mtf_is_exact_pupil_autocorrelation",
                     "pupil autocorrelation", 1e-12,
                     float((metrics.mtf(m128.uncoded_psf()) - ac.abs() / ac[0, 0]).abs().max())))
    for order, tol in ((1000.0, 5e-3), (50.0, 1.5e-2)):
        sp = OpticsSpec.with_samples_across(80, focal_n=256, supergaussian_order=order)
        radial = RadialMTF(sp)
        rad = radial(metrics.mtf(OpticalSystem(sp, dtype=F64).uncoded_psf()))
        sel = (radial.freqs > 0) & (radial.freqs < 0.95)
        rows.append(_row(A, f"uncoded radial MTF, edge order P = {order:g}", tp + "test_uncoded_radial_mtf_matches_"
                         "circular_pupil", "circular-pupil MTF (hard edge)", tol,
                         float((rad - circular_mtf(radial.freqs))[sel].abs().max())))
    worst = 0.0
    for method in ("mft", "fft"):
        ts = _native_spec(64, 192) if method == "fft" else spec
        s = OpticalSystem(ts, dtype=F64, method=method)
        for shift in (10.3, -7.6, 0.45):
            k = 2 * math.pi * shift * ts.focal_pitch_m / ts.focal_length_m / ts.wavelength_m
            psf = s.psf(k * s.grid.u[None, :].expand(s.grid.n, s.grid.n))
            iy, ix = divmod(int(psf.argmax()), 64)
            la, lb, lc = (math.log(float(psf[iy, ix + d])) for d in (-1, 0, 1))
            worst = max(worst, abs(ix - 32 + 0.5 * (la - lc) / (la - 2 * lb + lc) - shift))
    rows.append(_row(A, "tilted PSF peak position (MFT, FFT)", tp + "test_tilt_moves_peak_to_f_alpha",
                     "f alpha / dx", 0.05, worst, "0.05 px"))

    th = "tests/optics/test_halfring.py::"
    grid = OpticalSystem(spec, dtype=F64).grid
    wrap = lambda d: (torch.remainder(d + math.pi, 2 * math.pi) - math.pi).reshape(-1)[grid.support]  # noqa: E731
    err = 0.0
    for conv in ("atan2", "atan"):
        for sign in ("printed", "fourier"):
            ph = [HalfRingMask(grid, W_A, strategy=st, convention=conv, harmonic_sign=sign).phase().detach()
                  for st in ("exact", "direct")]
            err = max(err, float(wrap(ph[0] - ph[1]).abs().max()))
    rows.append(_row(A, "half-ring phase, distinct-radii evaluation", th + "test_exact_strategy_equals_direct",
                     "per-pixel Bessel evaluation", 1e-11, err, "1e-11 rad"))
    g32 = OpticalSystem(spec, dtype=F32).grid
    err = wrap(HalfRingMask(g32, W_A).phase().detach().double() - HalfRingMask(grid, W_A).phase().detach())
    rows.append(_row(A, "half-ring phase, float32 (RMS)", th + "test_exact_strategy_float32_close_to_float64",
                     "float64", 1e-4, float(err.pow(2).mean().sqrt()), "1e-04 rad"))
    tiny = OpticalSystem(OpticsSpec.with_samples_across(24, focal_n=32), dtype=F64)
    worst = 0.0
    for conv in ("atan2", "atan"):
        for sign in ("printed", "fourier"):
            mask = HalfRingMask(tiny.grid, W_A, convention=conv, harmonic_sign=sign)

            def lsr(r, t, mask=mask):
                ph = torch.func.functional_call(mask, {"r": r, "theta": t}, ())
                return metrics.lsr_smooth(tiny.psf(ph), tiny.uncoded_peak, p=16.0)

            worst = max(worst, _jacobian_error(lsr, [torch.tensor(PUBLISHED_R, dtype=F64),
                                                     torch.tensor(PUBLISHED_THETA, dtype=F64)], 1e-6, 1e-7, 1e-4))
    rows.append(_row(A, "d smooth LSR / d (r_n, theta_n)", th + "test_gradcheck_ring_parameters_to_smooth_lsr",
                     "central differences, eps 1e-6", 1.0, worst, "atol 1e-7 + rtol 1e-4"))
    return rows


# ---- sensor -------------------------------------------------------------------------------------------------
def _sensor_kit():
    """The tests' small geometry (tests/sensor/_util.py): 48 samples across, 33 x 33 window, published mask."""
    from codesign.data.params import fixed_scene_params
    from codesign.optics import OpticalSystem, OpticsSpec
    from codesign.optics.masks import published_halfring
    from codesign.sensor.simulator import SensorSimulator, psf_state
    from codesign.sensor.spec import SensorSpec

    quiet = dict(alpha_l=0.0, alpha_b=0.0, laser_angle_rad=0.0, c1=0.0, c2=0.0, dark_current_mean_e=0.0,
                 read_noise_mean_e=0.0, read_noise_std_e=0.0)
    optics, states = OpticsSpec.with_samples_across(48, focal_n=33), {}
    for dtype in (F64, F32):
        s = OpticalSystem(optics, dtype=dtype)
        with torch.no_grad():
            states[dtype] = (psf_state(s, published_halfring(s.grid, optics.aperture_diameter_m).phase()),
                             psf_state(s, torch.zeros_like(s.grid.aperture)))

    def sim(resolution, image_size, **kw):
        kw.setdefault("background_veil", False)
        return SensorSimulator(SensorSpec(resolution=resolution, image_size=image_size, padded_size=image_size, **kw),
                               optics)

    def params(batch=1, dtype=F64, **values):
        return fixed_scene_params(batch, dtype=dtype, **{**quiet, **values})

    def angle(sm, row, col):
        n, f, p = sm.coarse.n_sensor, optics.focal_length_m, sm.coarse.pitch
        return ((col - (n - 1) / 2) * p / f, (row - (n - 1) / 2) * p / f)

    def scene(sm, value=None, batch=1, seed=0, dtype=F64):
        s = sm.scene_size
        if value is not None:
            return torch.full((batch, 1, s, s), float(value), dtype=dtype)
        return torch.rand(batch, 1, s, s, generator=torch.Generator().manual_seed(seed), dtype=F64).to(dtype)

    return states, sim, params, angle, scene


def _z(x: torch.Tensor, mean: float, var: float) -> float:
    """Largest |z| of the sample mean and variance against their closed forms (standard errors from the sample)."""
    x = x.reshape(-1).double()
    n, m = x.numel(), float(x.mean())
    d = x - m
    s2, m4 = float((d**2).mean()), float((d**4).mean())
    return max(abs(m - mean) / math.sqrt(max(s2, 1e-300) / n), abs(s2 - var) / math.sqrt(max(m4 - s2**2, 1e-300) / n))


def sensor_rows(scale: str) -> list[dict]:
    from codesign.sensor.noise import NoiseStreams, dark_current, photons, read_noise

    A, rows, tn = "sensor", [], "tests/sensor/test_noise.py::"
    side = 640 if scale == "quick" else 1280
    col = lambda v: torch.tensor(v, dtype=F64).reshape(1, 1, 1, 1)  # noqa: E731
    zmax = 0.0
    for mu, c1, c2, sc in [(1e3, 0.0, 1.0, 1.0), (1e4, 0.2, 1.0, 1.0), (50.0, 0.05, 0.9, 0.25), (2e5, 0.1, 1.1, 0.5),
                           (3e3, 0.25, 0.0, 1.0)]:
        om = photons(torch.full((1, 1, side, side), mu, dtype=F64), col(c1), col(c2), sc, NoiseStreams(11, CPU))
        zmax = max(zmax, _z(om, mu, (c2**2 * mu + c1**2 * mu**2) * sc**2))
    tol = "4.5 standard errors"
    rows.append(_row(A, "photon noise: mean, variance (5 cases)", tn + "test_photons_mean_and_variance",
                     "mu_p; c2^2 mu_p + c1^2 mu_p^2", 4.5, zmax, tol))
    like = torch.zeros(1, 1, side, side, dtype=F64)
    zmax = max(_z(dark_current(col(mc), like, ne, NoiseStreams(5, CPU)), mc, mc / ne)
               for mc, ne in [(0.002, 1.0), (0.002, 16.0), (3.0, 1.0), (3.0, 97.81), (0.5, 9.0)])
    rows.append(_row(A, "dark current: mean, variance (5 cases)", tn + "test_dark_current_is_poisson_averaged",
                     "Poisson(n mu_c) / n", 4.5, zmax, tol))
    zmax = max(_z(read_noise(col(mr), col(sr), like, sc, NoiseStreams(7, CPU)), mr, (sr * sc) ** 2)
               for mr, sr, sc in [(390.0, 10.5, 1.0), (350.0, 11.0, 0.25), (0.0, 3.0, 1 / 9.89)])
    rows.append(_row(A, "read noise: mean, variance (3 cases)", tn + "test_read_noise_mean_and_std",
                     "N(mu_r, (sigma_r / k)^2)", 4.5, zmax, tol))

    states, sim, params, angle, scene = _sensor_kit()
    coded, uncoded = states[F64]
    sm = sim(33, 11, path="direct")  # quantization only: G e + n_q - G e ~ N(0, 1 / (6 k^2)), k = bin factor
    out = sm(scene(sm, batch=256), params(256, alpha_b=0.9), coded, seed=2)
    s_ = sm.sensor
    err = out["sensor_dn"] - s_.gain_dn_per_e * (out["irradiance"] * s_.full_well_e).clamp(0, s_.full_well_e)
    var = 1.0 / s_.bin_factor**2 / 6
    n = err.numel()
    z = max(abs(float(err.mean())) / math.sqrt(var / n), abs(float((err**2).mean()) - var) / (var * math.sqrt(2 / n)))
    rows.append(_row(A, "quantization of the binned pixel: mean, variance", "tests/sensor/test_digitize.py::"
                     "test_direct_path_quantization_is_gaussian_of_the_binned_rounding_variance",
                     "N(0, 1 / (6 k^2))", 4.5, z, "4.5 standard errors"))
    tl = "tests/sensor/test_laser.py::"
    worst = 0.0
    for path in ("direct", "full"):
        for n, r, c in [(9, 4, 4), (10, 6, 6), (9, 1, 1), (9, 7, 7)]:
            sm = sim(n, n, path=path, pixel_integration=False)
            out = sm(scene(sm, 0.0), params(alpha_l=1234.5, laser_angle_rad=angle(sm, r, c)), uncoded, seed=0)
            worst = max(worst, abs(float(out["laser"].max()) / 1234.5 - 1))
    rows.append(_row(A, "uncoded laser peak", tl + "test_uncoded_laser_peak_is_alpha_l", "alpha_l", 1e-6, worst,
                     "1e-06 rel"))
    worst, sm = 0.0, sim(39, 13)  # bin factor 3: the 11-pixel kernel spans the 33-sample window
    cc = (sm.coarse.n_sensor - 1) / 2
    for d in (0.0, 0.3):
        out = sm(scene(sm, 0.0), params(alpha_l=1e5, laser_angle_rad=angle(sm, cc + d, cc + d)), coded, seed=0)
        got = float(out["laser"].sum()) * sm.coarse.bins
        worst = max(worst, abs(got / (1e5 * float(coded.psf.sum()) / coded.uncoded_peak) - 1))
    rows.append(_row(A, "laser energy after binning and sub-pixel shift", tl + "test_laser_energy_is_alpha_l_window_"
                     "energy_over_uncoded_peak", "alpha_l sum(h) / h0(0)", 1e-3, worst, "1e-03 rel"))
    ld, lf = (sim(33, 11, path=p)(scene(sim(33, 11, path=p), 0.0), params(alpha_l=1e3), coded, seed=0)["laser"]
              for p in ("direct", "full"))
    tol = 2e-3 * float(ld.max()) + 2e-3 * lf.abs()
    rows.append(_row(A, "direct vs full-resolution laser map", tl + "test_direct_and_full_laser_maps_agree",
                     "area average of the full path", 1.0, float(((ld - lf).abs() / tol).max()),
                     "2e-3 of peak + 2e-3 rel"))
    worst = 0.0
    for path in ("direct", "full"):
        sm = {dt: sim(66, 22, path=path) for dt in (F32, F64)}
        alphas = torch.tensor([0.0, 1.0, 1e2, 1e4, 1e6, 1e8], dtype=F64)
        for pos in (None, (7.3, 7.3), (21.0, 21.0)):
            a = 0.0 if pos is None else angle(sm[F64], *pos)
            outs = {}
            for dt in (F32, F64):
                p = params(6, dtype=dt, alpha_b=0.6, laser_angle_rad=a, c1=0.2, c2=1.0, dark_current_mean_e=0.002,
                           read_noise_mean_e=390.0, read_noise_std_e=10.5).replace(alpha_l=alphas.to(dt))
                outs[dt] = sm[dt](scene(sm[dt], batch=6, seed=4).to(dt), p, states[dt][0], seed=11)
            away = (outs[F64]["laser"] == 0) & (outs[F32]["laser"] == 0)
            worst = max(worst, float((outs[F32]["sensor_dn"].double() - outs[F64]["sensor_dn"])[away].abs().max()))
    rows.append(_row(A, "float32 simulation off the laser footprint, alpha_l <= 1e8",
                     "tests/stress/test_laser_sweep.py::test_float32_laser_sweep_matches_float64",
                     "float64 simulation, same noise", 1.0, worst, "1 DN"))
    rows.append(_row(A, "d sensor / d (r_n, theta_n), every noise term on", "tests/sensor/test_gradients.py::"
                     "test_gradcheck_direct_path_with_every_noise_term_on", "central differences, eps 1e-6", 1.0,
                     _sensor_gradcheck(params, angle, scene), "atol 1e-8 + rtol 1e-4"))
    return rows


def _sensor_gradcheck(params, angle, scene) -> float:
    from codesign.optics import HalfRingMask, OpticalSystem, OpticsSpec
    from codesign.optics.masks import PUBLISHED_R, PUBLISHED_THETA
    from codesign.sensor.simulator import SensorSimulator, psf_state
    from codesign.sensor.spec import SensorSpec

    spec = OpticsSpec.with_samples_across(24, focal_n=15)
    system = OpticalSystem(spec, dtype=F64)
    sm = SensorSimulator(SensorSpec(resolution=24, image_size=8, padded_size=10, path="direct"), spec)
    mask = HalfRingMask(system.grid, spec.aperture_diameter_m)
    p = params(2, alpha_b=0.5, alpha_l=20.0, laser_angle_rad=angle(sm, 3.3, 3.3), c1=0.2, c2=1.0,
               dark_current_mean_e=0.002, read_noise_mean_e=390.0, read_noise_std_e=10.5)
    sc = scene(sm, batch=2, seed=3)
    w = torch.randn(2, 1, 10, 10, generator=torch.Generator().manual_seed(0), dtype=F64)

    def f(r, t):
        ph = torch.func.functional_call(mask, {"r": r, "theta": t}, ())
        return (sm(sc, p, psf_state(system, ph), seed=5)["sensor"] * w).sum()

    return _jacobian_error(f, [torch.tensor(PUBLISHED_R, dtype=F64), torch.tensor(PUBLISHED_THETA, dtype=F64)],
                           1e-6, 1e-8, 1e-4)


# ---- restoration: Wiener, attention, losses -------------------------------------------------------------------
def _gaussian(k: int, sigma: float) -> np.ndarray:
    r = np.arange(k) - k // 2
    g = np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * sigma**2))
    return g / g.sum()


def _np_otf(kernel: np.ndarray, n: int) -> np.ndarray:
    k, big = kernel.shape[0], np.zeros((n, n))
    for i in range(k):
        for j in range(k):
            big[(i - k // 2) % n, (j - k // 2) % n] += kernel[i, j]
    return np.fft.fft2(big)


def _np_wiener(y, h, nsr):
    return np.real(np.fft.ifft2(np.fft.fft2(y) * np.conj(h) / (np.abs(h) ** 2 + nsr)))


def restoration_rows(scale: str) -> list[dict]:
    from torch.func import functional_call

    from codesign.models.losses import gradient_penalty
    from codesign.models import classical_wiener, otf_from_kernel
    from codesign.models.blocks import EfficientAttention
    from codesign.models.wiener import LearnableWiener

    A, rows, tw = "restoration", [], "tests/models/test_wiener.py::"
    rng = np.random.default_rng(0)
    err = 0.0
    for n in (20, 21):
        kernel = _gaussian(5, 1.2)
        kernel[0, 3] += 0.3  # asymmetric: conj(H) must be the conjugate
        y = rng.random((2, n, n))
        out = classical_wiener(torch.from_numpy(y), otf_from_kernel(torch.from_numpy(kernel), n), 3e-2).numpy()
        ref = np.stack([_np_wiener(im, _np_otf(kernel, n), 3e-2) for im in y])
        err = max(err, np.abs(out - ref).max())
    rows.append(_row(A, "classical Wiener filter", tw + "test_classical_wiener_equals_numpy_reference",
                     "numpy float64 closed form", 1e-10, err))
    kernel = 0.4 * _gaussian(5, 1.0)
    kernel[2, 2] += 0.6
    x = np.random.default_rng(1).random((32, 32))
    y = np.real(np.fft.ifft2(np.fft.fft2(x) * _np_otf(kernel, 32)))
    out = classical_wiener(torch.from_numpy(y), otf_from_kernel(torch.from_numpy(kernel), 32), 1e-12).numpy()
    rows.append(_row(A, "Wiener, nsr 1e-12, |H| >= 0.2", tw + "test_wiener_with_tiny_nsr_inverts_a_well_conditioned_"
                     "blur", "the unblurred image", 1e-8, np.abs(out - x).max()))
    for dtype in (F32, F64):
        torch.manual_seed(0)
        lw = LearnableWiener(3, gamma_init=0.05).to(dtype)
        with torch.no_grad():
            lw.rho.add_(torch.tensor([0.0, 1.0, -2.0], dtype=dtype))
        f = (torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(3), dtype=F64)
             * torch.tensor([1.0, 0.1, 3.0], dtype=F64).view(1, 3, 1, 1))
        k = _gaussian(5, 1.0)
        out = lw(f.to(dtype), otf_from_kernel(torch.from_numpy(k).to(dtype), 16)).detach().double().numpy()
        gam, h = lw.gamma.detach().double().numpy(), _np_otf(k, 16)
        ref = np.stack([np.stack([_np_wiener(f[b, i].numpy(), h, gam[i] / np.mean(f[b, i].numpy() ** 2))
                                  for i in range(3)]) for b in range(2)])
        name = "float32" if dtype == F32 else "float64"
        tol = 2e-5 * np.abs(ref).max() if dtype == F32 else 1e-10
        rows.append(_row(A, f"learnable Wiener G_v deconvolution, {name}", tw + f"test_learnable_wiener_closed_form_"
                         f"{name}", "Eq. (Deconvolution), numpy float64", tol, np.abs(out - ref).max(),
                         "2e-5 of max" if dtype == F32 else None))
    lw = LearnableWiener(2, gamma_init=0.1).double()
    otf = otf_from_kernel(torch.from_numpy(_gaussian(3, 0.8)), 8)
    f = torch.rand(1, 2, 8, 8, dtype=F64, generator=torch.Generator().manual_seed(5))
    rows.append(_row(A, "d G_v / d (features, rho)", tw + "test_learnable_wiener_gradcheck_input_and_rho",
                     "central differences, eps 1e-6", 1.0,
                     _jacobian_error(lambda f, r: functional_call(lw, {"rho": r}, (f, otf)), [f, lw.rho.detach()],
                                     1e-6, 1e-5, 1e-3), "atol 1e-5 + rtol 1e-3"))

    torch.manual_seed(0)
    att = EfficientAttention(6, key_channels=3).double()
    for m in (att.query, att.key, att.value):
        torch.nn.init.normal_(m.weight, std=1.0)
        torch.nn.init.normal_(m.bias, std=0.5)
    xa = torch.randn(2, 6, 5, 7, dtype=F64)
    conv = lambda c, z: torch.einsum("oi,bin->bon", c.weight[:, :, 0, 0], z) + c.bias[None, :, None]  # noqa: E731
    fl = xa.flatten(2)
    q = torch.softmax(conv(att.query, fl).transpose(1, 2), dim=2)
    kk = torch.softmax(conv(att.key, fl).transpose(1, 2), dim=1)
    ref = ((q @ kk.transpose(1, 2)) @ conv(att.value, fl).transpose(1, 2)).transpose(1, 2).reshape(xa.shape)
    rows.append(_row(A, "efficient attention (linear cost)", "tests/models/test_models.py::test_efficient_attention_"
                     "equals_the_explicit_n_by_n_product", "explicit N x N softmax attention", 1e-12,
                     float((att.attend(xa) - ref).detach().abs().max())))

    class Linear(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.randn(2, 5, 4, generator=torch.Generator().manual_seed(1), dtype=F64))

        def forward(self, z):
            return (z * self.w).flatten(1).sum(1, keepdim=True), [z]

    critic = Linear()
    real, fake = (torch.rand(3, 2, 5, 4, generator=torch.Generator().manual_seed(s), dtype=F64) for s in (0, 1))
    gp = float(gradient_penalty(critic, real, fake, generator=torch.Generator().manual_seed(0)).detach())
    exact = (float(critic.w.norm()) - 1) ** 2
    rows.append(_row(A, "WGAN gradient penalty, linear critic", "tests/models/test_losses.py::test_gradient_penalty_"
                     "linear_critic", "(||w|| - 1)^2", 1e-12, abs(gp / exact - 1), "1e-12 rel"))
    return rows


# ---- training -----------------------------------------------------------------------------------------------
# Upper bounds of tests/stress/test_training_stress.py (BOUNDS) for the terms reported here
STRESS_BOUNDS = {"critic_total": 1e4, "d2_gp": 1e3, "generator_total": 1e3, "rec2": 5.0}
STRONG = ["data.params.alpha_l_range=[1.0e6,1.0e8]", "data.image_size=32", "data.padded_size=48"]


def _trainer(steps: int, *overrides: str, seed: int = 0):
    """The tests' tiny restoration trainer (tests/train/_util.py), no validation or checkpoint writes."""
    import tempfile

    from tests.train._util import tiny_trainer

    return tiny_trainer(Path(tempfile.mkdtemp()), *overrides, seed=seed, steps=steps, val_every=0,
                        checkpoint_every=0, image_every=0)


def _joint_guard_ratio(steps: int) -> float:
    """max over steps of smooth LSR / lsr_max for the co-design trainer with a mask step 25x the default and
    no penalty (tests/train/test_joint_trainer.py's setup): only the feasibility guard keeps the constraint."""
    import tempfile

    from tests.train._util import joint_trainer

    tr = joint_trainer(Path(tempfile.mkdtemp()), steps=steps, mask_lr=0.5, penalty_weight=0.0)
    lsr_max, worst = tr.codesign.constraint.lsr_max, 0.0
    for _ in range(steps):
        tr.train_step()
        worst = max(worst, tr.codesign.constraint.measure(tr.codesign.mask) / lsr_max)
    return worst


def _nan_step_change(tr) -> float:
    """Largest change of any critic weight or critic Adam moment over one step whose gradient penalty is NaN."""
    import codesign.models.losses as L

    def critic_state():
        return ([p.detach().clone() for m in tr.model.critics() for p in m.parameters()]
                + [v.clone() for s in tr.opt_d.state.values() for v in s.values()])

    before, gp = critic_state(), L.gradient_penalty
    L.gradient_penalty = lambda *a, **k: gp(*a, **k) * float("nan")
    try:
        terms = tr.train_step()
    finally:
        L.gradient_penalty = gp
    if terms.get("critic_skipped") != 1.0:
        return math.inf
    return max(float((x - y).abs().max()) for x, y in zip(before, critic_state()))


def training_rows(scale: str) -> list[dict]:
    import logging

    logger = logging.getLogger("codesign")
    level = logger.level
    logger.setLevel(logging.ERROR)  # the forced NaN logs a warning by design
    try:
        return _training_rows(scale)
    finally:
        logger.setLevel(level)


def _training_rows(scale: str) -> list[dict]:
    from codesign.train.checkpoint import load_checkpoint

    A, rows, tt = "training", [], "tests/train/test_trainer.py::"
    a = _trainer(4)
    a.train_step()
    a.train_step()
    path = a.save(a.run_dir / "ck.pt")
    later = [a.train_step() for _ in range(2)]
    b = _trainer(4, seed=123)
    b.load_state_dict(load_checkpoint(path))
    again = [b.train_step() for _ in range(2)]
    diff = max(max(abs(x[k] - y[k]) for k in x) for x, y in zip(later, again))
    diff = max(diff, max(float((p - q).abs().max()) for p, q in zip(a.model.parameters(), b.model.parameters())))
    rows.append(_row(A, "resume: 2 steps after a checkpoint", tt + "test_resume_reproduces_the_next_steps_exactly",
                     "the uninterrupted run", 0.0, diff, "0 (bit-identical)"))

    n = 4 if scale == "quick" else 40
    rows.append(_row(A, f"smooth LSR / lsr_max, {n} joint steps, mask_lr 0.5, no penalty", "tests/train/"
                     "test_joint.py::test_learned_mask_never_ends_above_lsr_max_under_a_large_mask_step",
                     "lsr_max (the published mask's)", 1 + 1e-6, _joint_guard_ratio(n), "1 + 1e-6"))

    steps = 60 if scale == "quick" else 300
    tr = _trainer(steps, *STRONG)
    val = tr.data.validation_batch(4)

    def rec():
        with torch.no_grad():
            t = tr.update.generator_losses(val, tr.model(val["sensor"], tr.data.otf))
        return torch.stack([t["rec1"], t["rec2"]])

    before, logs = rec(), []
    for k in range(steps):
        if k == steps // 2:  # a NaN gradient penalty mid-run: the critic update must be skipped
            rows.append(_row(A, "critics + their Adam moments across a NaN-loss step", "tests/stress/test_training_"
                             "stress.py::test_forced_nans_mid_run_skip_only_the_poisoned_update_and_training_recovers",
                             "their values before the step", 0.0, _nan_step_change(tr), "0 (unchanged)"))
            continue
        logs.append(tr.train_step())
    ts = ("tests/stress/test_training_stress.py::"
          "test_long_wgan_gp_run_under_strong_lasers_stays_finite_bounded_and_learns")
    for key, bound in STRESS_BOUNDS.items():
        vals = [abs(t[key]) for t in logs]
        ok = all(math.isfinite(v) for v in vals)
        rows.append(_row(A, f"max |{key}|, {steps} steps, alpha_l in [1e6, 1e8]", ts, "bound set from measured "
                         "ranges", bound, max(vals) if ok else float("nan"), f"{bound:g}"))
    rows.append(_row(A, f"validation rec1, rec2 after / before {steps} steps (larger)", ts, "learning under dazzle",
                     0.85, float((rec() / before).max()), "< 0.85"))
    return rows


# ---- the suite interface ------------------------------------------------------------------------------------
AREAS = {"optics": optics_rows, "sensor": sensor_rows, "restoration": restoration_rows, "training": training_rows}
TITLES = {"optics": "Optics", "sensor": "Sensor", "restoration": "Restoration: Wiener, attention, losses",
          "training": "Training"}


def measure(scale: str) -> dict:
    rows, seconds = [], {}
    for area, fn in AREAS.items():
        t0 = time.perf_counter()
        rows += fn(scale)
        seconds[area] = time.perf_counter() - t0
        print(f"  {area}: {seconds[area]:.1f} s", flush=True)
    return {"rows": rows, "seconds": seconds}


def table(rows: list[dict]) -> str:
    esc = lambda text: text.replace("|", "\\|")  # noqa: E731  (a bare | would split the markdown cell)
    return markdown_table(["check", "test", "reference", "tolerance", "measured max", "of tol"],
                          [[esc(r["check"]), f"`{r['test'].split('::')[-1]}`", esc(r["reference"]),
                            r["tolerance"], r["measured"], "-" if r["of_tol"] is None else r["of_tol"]] for r in rows],
                          {"measured max": ".2e", "of tol": ".2g"})


def run(scale: str, out: Path) -> Report:
    from benchmarks.common import machine

    data = measure(scale)
    write_json(out / "accuracy.json", {"machine": machine(), "scale": scale, **data})
    tables = [f"**{TITLES[a]}**\n\n" + table([r for r in data["rows"] if r["area"] == a]) for a in AREAS]
    failing = [r["check"] for r in data["rows"] if r["measured"] > r["tol"] or not math.isfinite(r["measured"])]
    notes = ["Largest error of each accuracy check next to the tolerance its test asserts (\"of tol\" = measured / "
             "tolerance; tolerance 0 means bit-identical). Finite-difference rows: max |analytic - numerical| / "
             "(atol + rtol |numerical|) over the whole Jacobian; noise rows: largest |z| of the sample mean and "
             "variance against the closed form. What each check means: [accuracy.md](accuracy.md).",
             "Every check within its tolerance." if not failing else "OUTSIDE TOLERANCE: " + "; ".join(failing)]
    rep = Report("accuracy", "Accuracy checks: measured maxima against the tests' tolerances", tables, [], notes)
    print("\n\n".join(rep.tables))
    return rep


if __name__ == "__main__":
    from benchmarks.__main__ import standalone

    standalone(run)
