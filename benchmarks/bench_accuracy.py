"""Accuracy: the largest errors of the checks the tests make, measured next to the tolerances they assert.

Each row runs one test's comparison (closed form, scipy, float64 reference, the other propagator, finite
differences, noise moments against their closed forms, an uninterrupted run) through the functions and tolerance
constants its test module exports (tests/...: the test asserts the same function against the same constant), so
a reference and its tolerance live in the test only; the row reports the largest error over the test's cases, and
"of tol" = measured / tolerance (below 1: the test passes with that much room). Finite-difference rows take the
test's function, inputs, eps, atol and rtol and report max |analytic - numerical| / (atol + rtol |numerical|) over
the whole Jacobian (what torch.autograd.gradcheck compares against 1 without returning it). Noise rows report the
largest |z| = |estimate - closed form| / standard error. docs/accuracy.md quotes these numbers.

    python -m benchmarks.bench_accuracy --scale quick
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import torch

from benchmarks.common import Report, finish, markdown_table

F64, F32 = torch.float64, torch.float32


def _row(area, check, test, reference, tol, measured, tol_text=None) -> dict:
    return {"area": area, "check": check, "test": test, "reference": reference, "tolerance": tol_text or f"{tol:.2g}",
            "tol": float(tol), "measured": float(measured), "of_tol": float(measured) / tol if tol else None}


def _short(x: float) -> str:
    """1e-06 -> '1e-6', 0.002 -> '2e-3' (one significant digit)."""
    return f"{x:.0e}".replace("e-0", "e-")


def _worst(values) -> float:
    """The largest of ``values``, NaN if any is NaN (the built-in max may skip a NaN)."""
    values = [float(v) for v in values]
    return math.nan if any(math.isnan(v) for v in values) else max(values)


def _dtype_name(dtype: torch.dtype) -> str:
    return "float64" if dtype == F64 else "float32"


def _gradcheck_reference(tol: dict) -> str:
    return f"central differences, eps {_short(tol['eps'])}"


def _gradcheck_tol(tol: dict) -> str:
    return f"atol {_short(tol['atol'])} + rtol {_short(tol['rtol'])}"


def _jacobian_error(fn, inputs, eps: float, atol: float, rtol: float) -> float:
    """max over Jacobian entries of |analytic - central difference| / (atol + rtol |central difference|) (NaN if any
    entry is NaN): torch.autograd.gradcheck(fn, inputs, eps=eps, atol=atol, rtol=rtol) passes its Jacobian
    comparison where this is at most 1."""
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
            ratio = float(((a[:, j] - num).abs() / (atol + rtol * num.abs())).max())
            if math.isnan(ratio):
                return math.nan
            worst = max(worst, ratio)
    return worst


# ---- optics -------------------------------------------------------------------------------------------------
def optics_rows(scale: str) -> list[dict]:
    from tests.optics.test_bessel import (BESSEL_ATOL, BESSEL_GRADCHECK_TOL, BESSEL_GRADIENT_ATOL, GRADCHECK_X0, N_MAX,
                                          N_MAX_CASES, bessel_error, bessel_gradcheck_case, bessel_gradient_errors)
    from tests.optics.test_halfring import (CONVENTIONS, EXACT_DIRECT_TOL, FLOAT32_PHASE_RMS_TOL, HARMONIC_SIGNS,
                                            LSR_GRADCHECK_TOL, exact_direct_error, float32_phase_rms,
                                            lsr_gradcheck_case)
    from tests.optics.test_psf import (AIRY_PATTERN_TOL, FFT_ENERGY_ATOL, FIRST_ZERO, FIRST_ZERO_RTOL,
                                       MFT_ENERGY_ATOL, MFT_FFT_TOL, MTF_AUTOCORRELATION_ATOL, RADIAL_MTF_TOL,
                                       RESAMPLED_TOL, TILT_AXES, TILT_METHODS, TILT_SHIFTS_PX, TILT_TOL_PX,
                                       UNCODED_PEAK_RTOL, fft_energy_errors, fft_resampled_errors, first_zero_error,
                                       mft_energy_errors, mft_fft_errors, mtf_autocorrelation_error, radial_mtf_error,
                                       tilt_error, uncoded_peak_error, uncoded_psf_airy_error)

    A, rows = "optics", []
    tb = "tests/optics/test_bessel.py::"
    # J_0..J_n on the tests' grid (uniform over [0, 1000], log-spaced from 1e-6, dense below 80 and around the
    # algorithm's switch points); the full scale asks for 10x more uniform points
    uniform = 4001 if scale == "quick" else 40001
    for dtype in (F64, F32):
        name = _dtype_name(dtype)
        cases = N_MAX_CASES if dtype == F64 else [N_MAX]  # the float32 test checks n_max = 60 only
        err = _worst(bessel_error(n, dtype, uniform) for n in cases)
        rows.append(_row(A, f"J_n, n <= 60, x in [0, 1000], {name}", tb + f"test_bessel_{name}_matches_scipy_to_"
                         + ("1e10" if dtype == F64 else "1e5"), "scipy.special.jv", BESSEL_ATOL[dtype], err))
        rows.append(_row(A, f"dJ_n/dx, {name}", tb + "test_bessel_gradient_matches_recurrence_derivative",
                         "(J_{n-1} - J_{n+1}) / 2 with scipy", BESSEL_GRADIENT_ATOL[dtype],
                         _worst(bessel_gradient_errors(dtype))))
    worst = _worst(_jacobian_error(*bessel_gradcheck_case(x0), **BESSEL_GRADCHECK_TOL) for x0 in GRADCHECK_X0)
    rows.append(_row(A, f"J_n gradient at {len(GRADCHECK_X0)} points, float64", tb + "test_bessel_gradcheck_float64",
                     _gradcheck_reference(BESSEL_GRADCHECK_TOL), 1.0, worst, _gradcheck_tol(BESSEL_GRADCHECK_TOL)))

    tp = "tests/optics/test_psf.py::"
    rows.append(_row(A, "uncoded peak h0(0)", tp + "test_uncoded_peak_matches_airy_peak", "Airy peak pi W_a^2 dx^2 / "
                     "(4 (lambda f)^2)", UNCODED_PEAK_RTOL, uncoded_peak_error(), f"{UNCODED_PEAK_RTOL:.0e} rel"))
    rows.append(_row(A, "uncoded PSF, 64 x 64 window", tp + "test_uncoded_psf_matches_airy_pattern",
                     "Airy pattern (hard edge)", AIRY_PATTERN_TOL, uncoded_psf_airy_error(),
                     f"{AIRY_PATTERN_TOL:.0e} of peak"))
    rows.append(_row(A, "first dark ring of the uncoded PSF", tp + "test_uncoded_first_zero_at_1p22_lambda_f_over_d",
                     f"{FIRST_ZERO} lambda f / W_a", FIRST_ZERO_RTOL, first_zero_error(), f"{FIRST_ZERO_RTOL:.0e} rel"))
    for dtype in (F64, F32):
        rows.append(_row(A, f"energy of the whole plane (FFT, native pitch), {_dtype_name(dtype)}",
                         tp + "test_fft_native_pitch_whole_plane_sums_to_one", "Parseval: 1", FFT_ENERGY_ATOL[dtype],
                         _worst(fft_energy_errors(dtype).values())))
    rows.append(_row(A, "energy of one replica period (MFT)", tp + "test_mft_whole_period_sums_to_one", "Parseval: 1",
                     MFT_ENERGY_ATOL, _worst(mft_energy_errors().values())))
    for dtype in (F64, F32):
        tol = MFT_FFT_TOL[dtype]
        rows.append(_row(A, f"MFT vs FFT on the same window, {_dtype_name(dtype)}",
                         tp + ("test_mft_equals_fft_on_the_same_window" if dtype == F64 else
                               "test_mft_equals_fft_in_float32"), "the other propagator", tol,
                         _worst(mft_fft_errors(dtype).values()), f"{tol:.0e} of peak"))
    rows.append(_row(A, "FFT resampled to the sensor pitch vs MFT", tp + "test_fft_resampled_onto_sensor_pitch_"
                     "approximates_mft", "MFT (exact)", RESAMPLED_TOL, _worst(fft_resampled_errors().values()),
                     f"{RESAMPLED_TOL:.0e} of peak"))
    rows.append(_row(A, "uncoded MTF (window = one period)", tp + "test_uncoded_mtf_is_exact_pupil_autocorrelation",
                     "pupil autocorrelation", MTF_AUTOCORRELATION_ATOL, mtf_autocorrelation_error()))
    for order, tol in RADIAL_MTF_TOL.items():
        rows.append(_row(A, f"uncoded radial MTF, edge order P = {order:g}", tp + "test_uncoded_radial_mtf_matches_"
                         "circular_pupil", "circular-pupil MTF (hard edge)", tol, radial_mtf_error(order)))
    worst = _worst(tilt_error(m, a, s) for m in TILT_METHODS for a in TILT_AXES for s in TILT_SHIFTS_PX)
    rows.append(_row(A, "tilted PSF peak position (MFT, FFT)", tp + "test_tilt_moves_peak_to_f_alpha",
                     "f alpha / dx", TILT_TOL_PX, worst, f"{TILT_TOL_PX:g} px"))

    th = "tests/optics/test_halfring.py::"
    err = _worst(exact_direct_error(c, h) for c in CONVENTIONS for h in HARMONIC_SIGNS)
    rows.append(_row(A, "half-ring phase, distinct-radii evaluation", th + "test_exact_strategy_equals_direct",
                     "per-pixel Bessel evaluation", EXACT_DIRECT_TOL, err, f"{EXACT_DIRECT_TOL:.0e} rad"))
    rows.append(_row(A, "half-ring phase, float32 (RMS)", th + "test_exact_strategy_float32_close_to_float64",
                     "float64", FLOAT32_PHASE_RMS_TOL, float32_phase_rms(), f"{FLOAT32_PHASE_RMS_TOL:.0e} rad"))
    worst = _worst(_jacobian_error(*lsr_gradcheck_case(c, h), **LSR_GRADCHECK_TOL)
                for c in CONVENTIONS for h in HARMONIC_SIGNS)
    rows.append(_row(A, "d smooth LSR / d (r_n, theta_n)", th + "test_gradcheck_ring_parameters_to_smooth_lsr",
                     _gradcheck_reference(LSR_GRADCHECK_TOL), 1.0, worst, _gradcheck_tol(LSR_GRADCHECK_TOL)))
    return rows


# ---- sensor -------------------------------------------------------------------------------------------------
def sensor_rows(scale: str) -> list[dict]:
    from tests.sensor.test_digitize import DIRECT_QUANTIZATION_GEOMETRIES, QUANTIZATION_Z, direct_quantization_z
    from tests.sensor.test_gradients import GRADCHECK_TOL, direct_path_gradcheck_case
    from tests.sensor.test_laser import (DIRECT_FULL_ATOL_OF_PEAK, DIRECT_FULL_RTOL, ENERGY_GEOMETRIES,
                                         ENERGY_OFFSETS, LASER_ENERGY_RTOL, LASER_PATHS, UNCODED_LASER_PEAK_RTOL,
                                         UNCODED_PEAK_CASES, direct_full_laser_ratio, laser_energy_error,
                                         uncoded_laser_peak_error)
    from tests.sensor.test_noise import (DARK_CASES, PHOTON_CASES, READ_CASES, Z, dark_sample, mean_var_z,
                                         photon_sample, read_sample)
    from tests.stress.test_laser_sweep import AWAY_TOL_DN, PATHS, POSITIONS, float32_away_error

    A, rows, tn = "sensor", [], "tests/sensor/test_noise.py::"
    side = 640 if scale == "quick" else 1280  # 409,600 draws per statistic in the tests (N_SIDE = 640)
    tol = f"{Z:g} standard errors"
    rows.append(_row(A, f"photon noise: mean, variance ({len(PHOTON_CASES)} cases)", tn + "test_photons_mean_and_"
                     "variance", "mu_p; c2^2 mu_p + c1^2 mu_p^2", Z,
                     _worst(mean_var_z(*photon_sample(*c, side=side)) for c in PHOTON_CASES), tol))
    rows.append(_row(A, f"dark current: mean, variance ({len(DARK_CASES)} cases)", tn + "test_dark_current_is_"
                     "poisson_averaged", "Poisson(n mu_c) / n", Z,
                     _worst(mean_var_z(*dark_sample(*c, side=side)) for c in DARK_CASES), tol))
    rows.append(_row(A, f"read noise: mean, variance ({len(READ_CASES)} cases)", tn + "test_read_noise_mean_and_std",
                     "N(mu_r, (sigma_r / k)^2)", Z, _worst(mean_var_z(*read_sample(*c, side=side)) for c in READ_CASES),
                     tol))
    z = _worst(direct_quantization_z(*g) for g in DIRECT_QUANTIZATION_GEOMETRIES)
    rows.append(_row(A, "quantization of the binned pixel: mean, variance", "tests/sensor/test_digitize.py::"
                     "test_direct_path_quantization_is_gaussian_of_the_binned_rounding_variance",
                     "N(0, 1 / (6 k^2))", QUANTIZATION_Z, z, f"{QUANTIZATION_Z:g} standard errors"))
    tl = "tests/sensor/test_laser.py::"
    worst = _worst(uncoded_laser_peak_error(p, *c) for p in LASER_PATHS for c in UNCODED_PEAK_CASES)
    rows.append(_row(A, "uncoded laser peak", tl + "test_uncoded_laser_peak_is_alpha_l", "alpha_l",
                     UNCODED_LASER_PEAK_RTOL, worst, f"{UNCODED_LASER_PEAK_RTOL:.0e} rel"))
    worst = _worst(laser_energy_error(*g.values, dy, dx) for g in ENERGY_GEOMETRIES for dy, dx in ENERGY_OFFSETS)
    rows.append(_row(A, "laser energy after binning and sub-pixel shift", tl + "test_laser_energy_is_alpha_l_window_"
                     "energy_over_uncoded_peak", "alpha_l sum(h) / h0(0)", LASER_ENERGY_RTOL, worst,
                     f"{LASER_ENERGY_RTOL:.0e} rel"))
    rows.append(_row(A, "direct vs full-resolution laser map", tl + "test_direct_and_full_laser_maps_agree",
                     "area average of the full path", 1.0, direct_full_laser_ratio(),
                     f"{_short(DIRECT_FULL_ATOL_OF_PEAK)} of peak + {_short(DIRECT_FULL_RTOL)} rel"))
    worst = _worst(float32_away_error(p, w) for p in PATHS for w in POSITIONS)
    rows.append(_row(A, "float32 simulation off the laser footprint, alpha_l <= 1e8",
                     "tests/stress/test_laser_sweep.py::test_float32_laser_sweep_matches_float64",
                     "float64 simulation, same noise", AWAY_TOL_DN, worst, f"{AWAY_TOL_DN:g} DN"))
    _, f, inputs = direct_path_gradcheck_case()
    rows.append(_row(A, "d sensor / d (r_n, theta_n), every noise term on", "tests/sensor/test_gradients.py::"
                     "test_gradcheck_direct_path_with_every_noise_term_on", _gradcheck_reference(GRADCHECK_TOL), 1.0,
                     _jacobian_error(f, inputs, **GRADCHECK_TOL), _gradcheck_tol(GRADCHECK_TOL)))
    return rows


# ---- restoration: Wiener, attention, losses -------------------------------------------------------------------
def restoration_rows(scale: str) -> list[dict]:
    from tests.models.test_losses import GP_LINEAR_RTOL, gradient_penalty_linear_error
    from tests.models.test_models import ATTENTION_ATOL, attention_error
    from tests.models.test_wiener import (CLASSICAL_ATOL, CLASSICAL_SIZES, LEARNABLE_F32_OF_MAX, LEARNABLE_F64_ATOL,
                                          LEARNABLE_GRADCHECK_TOL, TINY_NSR_ATOL, classical_wiener_error,
                                          learnable_wiener_float32_error, learnable_wiener_float64_error,
                                          learnable_wiener_gradcheck_case, tiny_nsr_inversion_error)

    A, rows, tw = "restoration", [], "tests/models/test_wiener.py::"
    rows.append(_row(A, "classical Wiener filter", tw + "test_classical_wiener_equals_numpy_reference",
                     "numpy float64 closed form", CLASSICAL_ATOL,
                     _worst(classical_wiener_error(n) for n in CLASSICAL_SIZES)))
    rows.append(_row(A, "Wiener, nsr 1e-12, |H| >= 0.2", tw + "test_wiener_with_tiny_nsr_inverts_a_well_conditioned_"
                     "blur", "the unblurred image", TINY_NSR_ATOL, tiny_nsr_inversion_error()))
    rows.append(_row(A, "learnable Wiener G_v deconvolution, float32", tw + "test_learnable_wiener_closed_form_float32",
                     "Eq. (Deconvolution), numpy float64", LEARNABLE_F32_OF_MAX, learnable_wiener_float32_error(),
                     f"{_short(LEARNABLE_F32_OF_MAX)} of max"))
    rows.append(_row(A, "learnable Wiener G_v deconvolution, float64", tw + "test_learnable_wiener_closed_form_float64",
                     "Eq. (Deconvolution), numpy float64", LEARNABLE_F64_ATOL, learnable_wiener_float64_error()))
    rows.append(_row(A, "d G_v / d (features, rho)", tw + "test_learnable_wiener_gradcheck_input_and_rho",
                     _gradcheck_reference(LEARNABLE_GRADCHECK_TOL), 1.0,
                     _jacobian_error(*learnable_wiener_gradcheck_case(), **LEARNABLE_GRADCHECK_TOL),
                     _gradcheck_tol(LEARNABLE_GRADCHECK_TOL)))
    rows.append(_row(A, "efficient attention (linear cost)", "tests/models/test_models.py::test_efficient_attention_"
                     "equals_the_explicit_n_by_n_product", "explicit N x N softmax attention", ATTENTION_ATOL,
                     attention_error()))
    rows.append(_row(A, "WGAN gradient penalty, linear critic", "tests/models/test_losses.py::test_gradient_penalty_"
                     "linear_critic", "(||w|| - 1)^2", GP_LINEAR_RTOL, gradient_penalty_linear_error(),
                     f"{GP_LINEAR_RTOL:.0e} rel"))
    return rows


# ---- training -----------------------------------------------------------------------------------------------
# the terms of tests/stress/test_training_stress.py's BOUNDS reported here (that test also lets the penalty terms
# spike over their bound in a few single steps; see its SPIKY)
STRESS_TERMS = ("critic_total", "d2_gp", "generator_total", "rec2")


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
    import tempfile

    from tests.stress.test_training_stress import (BOUNDS, LEARNING_RATIO, NAN_STEP_TOL, NO_IO, STRONG_LASER,
                                                   learning_ratio, nan_penalty_step, validation_rec)
    from tests.train._util import tiny_trainer
    from tests.train.test_mask_codesign import guard_limit, large_mask_step_trainer, lsr_ratios
    from tests.train.test_trainer import RESUME_TOL, resume_difference

    A, rows = "training", []
    rows.append(_row(A, "resume: 2 steps after a checkpoint", "tests/train/test_trainer.py::test_resume_reproduces_"
                     "the_next_steps_exactly", "the uninterrupted run", RESUME_TOL,
                     resume_difference(tmp_path=Path(tempfile.mkdtemp())), "0 (bit-identical)"))

    n = 4 if scale == "quick" else 40  # the test: 4
    tr = large_mask_step_trainer(Path(tempfile.mkdtemp()), steps=n)
    worst = _worst(lsr_ratios(tr, n))
    rows.append(_row(A, f"smooth LSR / lsr_max, {n} joint steps, mask_lr 0.5, no penalty", "tests/train/"
                     "test_mask_codesign.py::test_learned_mask_never_ends_above_lsr_max_under_a_large_mask_step",
                     "lsr_max (the published mask's)", guard_limit(tr), worst,
                     f"1 + {_short(tr.codesign.spec.guard_tolerance)}"))

    steps = 60 if scale == "quick" else 300  # the test: 100 (600 in its slow level)
    tr = tiny_trainer(Path(tempfile.mkdtemp()), *STRONG_LASER, steps=steps, **NO_IO)
    before, logs = validation_rec(tr), []
    for k in range(steps):
        if k == steps // 2:  # a NaN gradient penalty mid-run: the critic update must be skipped
            rows.append(_row(A, "critics + their Adam moments across a NaN-loss step", "tests/stress/test_training_"
                             "stress.py::test_forced_nans_mid_run_skip_only_the_poisoned_update_and_training_recovers",
                             "their values before the step", NAN_STEP_TOL, nan_penalty_step(tr)[1], "0 (unchanged)"))
            continue
        logs.append(tr.train_step())
    ts = ("tests/stress/test_training_stress.py::"
          "test_long_wgan_gp_run_under_strong_lasers_stays_finite_bounded_and_learns")
    for key in STRESS_TERMS:
        bound, vals = BOUNDS[key], [abs(t[key]) for t in logs]
        ok = all(math.isfinite(v) for v in vals)
        rows.append(_row(A, f"max |{key}|, {steps} steps, alpha_l in [1e6, 1e8]", ts, "bound set from measured "
                         "ranges", bound, max(vals) if ok else float("nan"), f"{bound:g}"))
    rows.append(_row(A, f"validation rec1, rec2 after / before {steps} steps (larger)", ts, "learning under dazzle",
                     LEARNING_RATIO, learning_ratio(before, validation_rec(tr)), f"< {LEARNING_RATIO:g}"))
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
    data = measure(scale)
    tables = [f"**{TITLES[a]}**\n\n" + table([r for r in data["rows"] if r["area"] == a]) for a in AREAS]
    failing = [r["check"] for r in data["rows"] if r["measured"] > r["tol"] or not math.isfinite(r["measured"])]
    notes = ["Largest error of each accuracy check next to the tolerance its test asserts (\"of tol\" = measured / "
             "tolerance; tolerance 0 means bit-identical). Finite-difference rows: max |analytic - numerical| / "
             "(atol + rtol |numerical|) over the whole Jacobian; noise rows: largest |z| of the sample mean and "
             "variance against the closed form. What each check means: [accuracy.md](accuracy.md).",
             "Every check within its tolerance." if not failing else "OUTSIDE TOLERANCE: " + "; ".join(failing)]
    return finish(Report("accuracy", "Accuracy checks: measured maxima against the tests' tolerances", tables, [],
                         notes), out, scale, data)


if __name__ == "__main__":
    from benchmarks.__main__ import standalone

    standalone(run)
