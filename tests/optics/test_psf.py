"""Uncoded and coded PSFs: Airy pattern, energy conservation, MFT vs FFT, LSR of the uncoded PSF, tilt, MTF."""
from __future__ import annotations

import math

import pytest
import torch

from codesign.optics import (
    OpticalSystem,
    OpticsSpec,
    RadialMTF,
    airy_psf,
    circular_mtf,
    metrics,
    propagation,
)
from codesign.optics.grid import axis_coords
from codesign.optics.masks import published_halfring
from codesign.optics.propagation import (
    choose_propagator,
    czt_length,
    exact_fft_size,
    modelled_costs,
    next_fast_len,
)

S = 64  # pupil samples across the aperture for the small systems here


def _native_spec(focal_n: int, fft_n: int = 192, samples: int = S) -> OpticsSpec:
    """A spec whose focal pitch is the native pitch lambda f / (fft_n * pupil_pitch) of an fft_n-point FFT."""
    base = OpticsSpec.with_samples_across(samples, focal_n=16)
    pitch = base.lambda_f / (fft_n * base.pupil_pitch_m)
    return OpticsSpec.with_samples_across(samples, focal_n=focal_n, focal_pitch_m=pitch, fft_n=fft_n)


def _phases(system: OpticalSystem) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(1234)
    n = system.grid.n
    return {
        "zero": torch.zeros(n, n, dtype=system.dtype),
        "random": ((torch.rand(n, n, generator=g, dtype=torch.float64) * 2 - 1) * 5 * math.pi).to(system.dtype),
        "halfring": published_halfring(system.grid, system.spec.aperture_diameter_m).phase().detach(),
    }


def _focal_radius(spec: OpticsSpec) -> torch.Tensor:
    c = axis_coords(spec.focal_n, spec.focal_pitch_m, dtype=torch.float64)
    return torch.sqrt(c[:, None] ** 2 + c[None, :] ** 2)


def small_system64() -> OpticalSystem:
    """What the small_system64 fixture (tests/conftest.py) holds, for callers outside pytest
    (benchmarks/bench_accuracy.py): float64, 64 samples across, 64 x 64 window at the sensor pitch."""
    return OpticalSystem(OpticsSpec.with_samples_across(S, focal_n=64), dtype=torch.float64)


# ---- uncoded PSF vs the analytic Airy pattern ----------------------------------------------------------------
# Tolerances and the measured errors they bound (benchmarks/bench_accuracy.py reports these errors next to them)
UNCODED_PEAK_RTOL = 1e-2  # |h0(0) / Airy peak - 1|
AIRY_PATTERN_TOL = 1e-2  # max |uncoded PSF - Airy pattern| / Airy peak


def uncoded_peak_error(system: OpticalSystem | None = None) -> float:
    """|h0(0) / (pi W_a^2 dx^2 / (4 (lambda f)^2)) - 1| (super-Gaussian edge against the hard-edge Airy peak)."""
    system = small_system64() if system is None else system
    airy0 = float(airy_psf(torch.zeros(1, dtype=torch.float64), system.spec))
    return abs(system.uncoded_peak / airy0 - 1)


def uncoded_psf_airy_error(system: OpticalSystem | None = None) -> float:
    """max |uncoded PSF - Airy pattern| over the window, as a fraction of the Airy peak."""
    system = small_system64() if system is None else system
    airy = airy_psf(_focal_radius(system.spec), system.spec)
    return float((system.uncoded_psf() - airy).abs().max()) / float(airy.max())


def test_uncoded_peak_matches_airy_peak(small_system64, small_spec):
    # super-Gaussian (P = 50) vs hard edge: measured +0.27 %
    assert uncoded_peak_error(small_system64) <= UNCODED_PEAK_RTOL
    psf0 = small_system64.uncoded_psf()
    c = small_spec.focal_n // 2
    assert float(psf0[c, c]) == pytest.approx(small_system64.uncoded_peak, rel=1e-12)
    assert int(psf0.argmax()) == c * small_spec.focal_n + c


def test_uncoded_psf_matches_airy_pattern(small_system64, small_spec):
    psf0 = small_system64.uncoded_psf()
    assert uncoded_psf_airy_error(small_system64) <= AIRY_PATTERN_TOL  # measured 0.54 % of the peak
    # the PSF is symmetric under x -> -x and y -> -y and x <-> y
    core = psf0[1:, 1:]  # drop the unpaired first row/column of the even window
    torch.testing.assert_close(core, core.flip(0), rtol=1e-10, atol=1e-16)
    torch.testing.assert_close(core, core.flip(1), rtol=1e-10, atol=1e-16)
    torch.testing.assert_close(psf0, psf0.T, rtol=1e-10, atol=1e-16)


def test_airy_psf_first_zero_and_peak_formula():
    spec = OpticsSpec.with_samples_across(S, focal_n=16)
    r = torch.tensor([0.0, 1.2196698912665045 * spec.lambda_f_over_d], dtype=torch.float64)
    h = airy_psf(r, spec)
    peak = math.pi * spec.aperture_diameter_m**2 / 4 * spec.focal_pitch_m**2 / spec.lambda_f**2
    assert float(h[0]) == pytest.approx(peak, rel=1e-14)
    assert abs(float(h[1])) <= 1e-28


FIRST_ZERO = 1.2197  # the hard-edge Airy pattern's first zero, in lambda f / W_a
FIRST_ZERO_RTOL = 1e-2
PER_LFD = 40  # focal samples per lambda f / W_a


def _first_dark_ring() -> tuple[torch.Tensor, int, float]:
    """(the uncoded PSF along y = 0, x >= 0 at PER_LFD samples per lambda f / W_a; the index of its first minimum;
    the parabola-refined position of that minimum in lambda f / W_a)."""
    base = OpticsSpec.with_samples_across(S, focal_n=16)
    spec = OpticsSpec.with_samples_across(S, focal_n=128, focal_pitch_m=base.lambda_f_over_d / PER_LFD)
    system = OpticalSystem(spec, dtype=torch.float64, method="mft")
    c = spec.focal_n // 2
    line = system.uncoded_psf()[c, c:]  # y = 0, x >= 0
    i = int(torch.argmin(line[: 2 * PER_LFD]))
    y0, y1, y2 = (float(line[i + k]) for k in (-1, 0, 1))
    return line, i, (i + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)) / PER_LFD


def first_zero_error(x_zero: float | None = None) -> float:
    """|x_zero / 1.2197 - 1| for the first dark ring of the uncoded PSF (computed when not given)."""
    x_zero = _first_dark_ring()[2] if x_zero is None else x_zero
    return abs(x_zero / FIRST_ZERO - 1)


def test_uncoded_first_zero_at_1p22_lambda_f_over_d():
    per = PER_LFD
    line, i, x_zero = _first_dark_ring()
    assert per <= i <= 2 * per - 2
    assert first_zero_error(x_zero) <= FIRST_ZERO_RTOL  # measured 1.2273 (super-Gaussian edge: +0.6 %)
    assert float(line[i]) <= 1e-5 * float(line[0])


# ---- energy -------------------------------------------------------------------------------------------------
FFT_ENERGY_ATOL = {torch.float64: 1e-10, torch.float32: 1e-5}  # |energy of the whole plane - 1|
MFT_ENERGY_ATOL = 1e-10  # |energy of one replica period - 1|


def _energy_errors(system: OpticalSystem) -> dict[str, float]:
    """Per phase of _phases: |sum of the PSF (in float64) - 1|."""
    return {name: abs(float(system.psf(phase.to(system.dtype)).to(torch.float64).sum()) - 1)
            for name, phase in _phases(system).items()}


def fft_energy_errors(dtype: torch.dtype) -> dict[str, float]:
    """|energy - 1| of the FFT PSF on the whole plane at the native pitch (192 x 192), per phase."""
    return _energy_errors(OpticalSystem(_native_spec(focal_n=192, fft_n=192), dtype=dtype, method="fft"))


def mft_energy_errors() -> dict[str, float]:
    """|energy - 1| of the float64 MFT PSF on a window of one replica period at the native pitch, per phase."""
    return _energy_errors(OpticalSystem(_native_spec(focal_n=192, fft_n=192), dtype=torch.float64, method="mft"))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_fft_native_pitch_whole_plane_sums_to_one(dtype):
    spec = _native_spec(focal_n=192, fft_n=192)
    assert spec.focal_extent_m == pytest.approx(spec.replica_period_m, rel=1e-12)
    system = OpticalSystem(spec, dtype=dtype, method="fft")
    assert system.propagator.fft_n == 192
    assert system.propagator.resample is False
    assert system.propagator.native_pitch == pytest.approx(spec.focal_pitch_m, rel=1e-12)
    for name, phase in _phases(system).items():
        psf = system.psf(phase.to(dtype))
        assert psf.shape == (192, 192)
        assert psf.dtype == dtype
        assert float(psf.min()) >= 0
    for name, err in fft_energy_errors(dtype).items():
        assert err <= FFT_ENERGY_ATOL[dtype], name


def test_mft_whole_period_sums_to_one():
    # the MFT onto a window of one full replica period at the native pitch is the same DFT
    for name, err in mft_energy_errors().items():
        assert err <= MFT_ENERGY_ATOL, name


def test_energy_in_window_is_at_most_one(small_system64):
    for name, phase in _phases(small_system64).items():
        e = float(small_system64.psf(phase).sum())
        assert 0 < e <= 1 + 1e-12, name
    assert float(small_system64.uncoded_psf().sum()) == pytest.approx(1.0, abs=1e-2)


def test_psf_is_batched(small_system64):
    ph = _phases(small_system64)
    stack = torch.stack([ph["zero"], ph["random"], ph["halfring"]])
    batch = small_system64.psf(stack)
    assert batch.shape == (3, small_system64.spec.focal_n, small_system64.spec.focal_n)
    for k, name in enumerate(["zero", "random", "halfring"]):
        torch.testing.assert_close(batch[k], small_system64.psf(ph[name]), rtol=1e-12, atol=1e-18)


# ---- MFT vs FFT --------------------------------------------------------------------------------------------
MFT_FFT_TOL = {torch.float64: 1e-6, torch.float32: 1e-4}  # max |MFT PSF - FFT PSF| / MFT peak, same window
MFT_FFT_PHASES = {torch.float64: ("zero", "random", "halfring"), torch.float32: ("halfring",)}
RESAMPLED_TOL = 0.03  # the same, FFT at its native pitch bilinearly resampled onto the sensor pitch
RESAMPLED_PHASES = ("zero", "halfring")


def _relative_max_error(mft: OpticalSystem, fft: OpticalSystem, names) -> dict[str, float]:
    """Per phase name: max |MFT PSF - FFT PSF| / max |MFT PSF|."""
    errs = {}
    for name in names:
        phase = _phases(mft)[name]
        a, b = mft.psf(phase), fft.psf(phase)
        errs[name] = float((a - b).abs().max() / a.abs().max())
    return errs


def mft_fft_errors(dtype: torch.dtype) -> dict[str, float]:
    """MFT against FFT on the same 64 x 64 window at the FFT's native pitch, per phase of MFT_FFT_PHASES[dtype]."""
    spec = _native_spec(focal_n=64, fft_n=192)
    return _relative_max_error(*(OpticalSystem(spec, dtype=dtype, method=m) for m in ("mft", "fft")),
                               MFT_FFT_PHASES[dtype])


def fft_resampled_errors() -> dict[str, float]:
    """MFT against the FFT resampled onto the sensor pitch (fft_n = 560), per phase of RESAMPLED_PHASES."""
    spec = OpticsSpec.with_samples_across(S, focal_n=64, fft_n=560)
    return _relative_max_error(*(OpticalSystem(spec, dtype=torch.float64, method=m) for m in ("mft", "fft")),
                               RESAMPLED_PHASES)


def test_mft_equals_fft_on_the_same_window():
    spec = _native_spec(focal_n=64, fft_n=192)
    fft = OpticalSystem(spec, dtype=torch.float64, method="fft")
    assert fft.propagator.resample is False
    for name, err in mft_fft_errors(torch.float64).items():
        assert err <= MFT_FFT_TOL[torch.float64], f"{name}: relative max error {err:.3e}"  # measured ~2e-15


def test_mft_equals_fft_in_float32():
    for err in mft_fft_errors(torch.float32).values():
        assert err <= MFT_FFT_TOL[torch.float32]


def test_fft_resampled_onto_sensor_pitch_approximates_mft():
    # native pitch 2.6 x finer than the sensor pitch: bilinear resampling is close (measured 1.2 % of the peak)
    spec = OpticsSpec.with_samples_across(S, focal_n=64, fft_n=560)
    mft = OpticalSystem(spec, dtype=torch.float64, method="mft")
    fft = OpticalSystem(spec, dtype=torch.float64, method="fft")
    assert fft.propagator.resample is True
    for name, err in fft_resampled_errors().items():
        assert err <= RESAMPLED_TOL, name
    for name in RESAMPLED_PHASES:
        phase = _phases(mft)[name]
        a, b = mft.psf(phase), fft.psf(phase)
        assert float(b.sum()) == pytest.approx(float(a.sum()), abs=5e-3), name  # measured 2.2e-3


def test_fft_with_automatic_size_approximates_mft():
    # method='fft' with fft_n = null on a spec without an exact FFT size: the docstring promises the smallest
    # fast size >= the grid and bilinear resampling onto the window. The result should still approximate the
    # exact (MFT) PSF that the spec validated as alias-free at this focal pitch.
    spec = OpticsSpec.with_samples_across(S, focal_n=64)
    assert exact_fft_size(spec) is None
    mft = OpticalSystem(spec, dtype=torch.float64, method="mft")
    fft = OpticalSystem(spec, dtype=torch.float64, method="fft")
    a, b = mft.psf(_phases(mft)["zero"]), fft.psf(_phases(mft)["zero"])
    err = float((a - b).abs().max() / a.max())
    native_per_lfd = spec.lambda_f_over_d / fft.propagator.native_pitch
    assert err <= 0.05, (f"uncoded PSF via FFT (fft_n = {fft.propagator.fft_n}, native sampling "
                         f"{native_per_lfd:.3g} samples per lambda f / W_a) differs from MFT by {err:.3g} of the peak")


def test_next_fast_len_and_exact_fft_size():
    assert [next_fast_len(n) for n in (1, 2, 11, 13, 17, 97, 1068, 4096)] == [1, 2, 12, 14, 18, 98, 1080, 4096]
    spec = _native_spec(focal_n=64, fft_n=192)
    assert exact_fft_size(spec) == 192
    assert set(modelled_costs(spec)) == {"mft", "czt", "fft"}  # the FFT competes only where it is exact
    assert set(modelled_costs(OpticsSpec.with_samples_across(S, focal_n=64))) == {"mft", "czt"}
    assert choose_propagator(spec.replace(propagator="mft")) == "mft"
    for s in (spec, OpticsSpec.with_samples_across(S, focal_n=64), OpticsSpec(),
              OpticsSpec.with_samples_across(1024, focal_n=640)):
        costs = modelled_costs(s)
        assert choose_propagator(s) == min(costs, key=costs.get)
    # the chirp-z's cost grows like (n + m) L log L, the MFT's like n m (n + m): chirp-z wins at the paper's pupil
    assert choose_propagator(OpticsSpec.with_samples_across(1024, focal_n=640)) == "czt"


# ---- chirp-z -------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("samples,focal_n", [(S, 64), (S, 37), (40, 120), (33, 16)])
def test_czt_equals_mft_to_float64_rounding(samples, focal_n):
    """Odd and even grids and windows, windows wider and narrower than the pupil grid."""
    spec = OpticsSpec.with_samples_across(samples, focal_n=focal_n)
    mft = OpticalSystem(spec, dtype=torch.float64, method="mft")
    czt = OpticalSystem(spec, dtype=torch.float64, method="czt")
    for name, phase in _phases(mft).items():
        a, b = mft.psf(phase), czt.psf(phase)
        assert float((a - b).abs().max() / a.abs().max()) <= 1e-12, name  # measured ~4e-15
        assert float(b.sum()) == pytest.approx(float(a.sum()), rel=1e-12)


def test_czt_equals_fft_on_the_same_window_and_is_batched():
    spec = _native_spec(focal_n=64, fft_n=192)
    fft = OpticalSystem(spec, dtype=torch.float64, method="fft")
    czt = OpticalSystem(spec, dtype=torch.float64, method="czt")
    phases = torch.stack(list(_phases(fft).values()))
    a, b = fft.psf(phases), czt.psf(phases)
    assert b.shape == (3, 64, 64)
    assert float((a - b).abs().max() / a.abs().max()) <= 1e-12
    for i in range(3):
        torch.testing.assert_close(czt.psf(phases[i]), b[i], rtol=1e-13, atol=1e-18)


def test_czt_length_is_the_smallest_5_smooth_size_holding_the_taps():
    def smooth5(k: int) -> bool:
        for p in (2, 3, 5):
            while k % p == 0:
                k //= p
        return k == 1

    for n, m in ((402, 640), (1066, 640), (202, 160), (13, 20), (1, 1)):
        length = czt_length(n, m)
        assert smooth5(length) and length >= n + m - 1
        assert not any(smooth5(k) for k in range(n + m - 1, length))
    assert (czt_length(402, 640), czt_length(1066, 640)) == (1080, 1728)  # next_fast_len (radix 7): 1050, 1715


def test_czt_in_row_blocks_equals_one_batch_with_gradients(monkeypatch):
    """The CPU blocks (CZT_ROWS_PER_THREAD) only regroup rows: a batch of phases through blocks of 3 rows per
    thread (uneven last block, blocks across the batch's fields) equals one block, forward and backward."""
    spec = OpticsSpec.with_samples_across(40, focal_n=50)
    czt = OpticalSystem(spec, dtype=torch.float64, method="czt")
    phases = torch.stack([_phases(czt)["random"], _phases(czt)["halfring"]]).requires_grad_(True)
    weights = torch.rand(50, 50, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    results = []
    for rows in (3, 10_000):
        monkeypatch.setattr(propagation, "CZT_ROWS_PER_THREAD", rows)
        psf = czt.psf(phases)
        (grad,) = torch.autograd.grad((psf * weights).sum(), phases)
        results.append((psf, grad))
    assert all(2 * k % (3 * torch.get_num_threads()) for k in (czt.grid.n, 50))  # short last blocks, both passes
    torch.testing.assert_close(results[0][0], results[1][0], rtol=1e-13, atol=1e-18)
    torch.testing.assert_close(results[0][1], results[1][1], rtol=1e-11, atol=1e-16)
    mft = OpticalSystem(spec, dtype=torch.float64, method="mft").psf(phases.detach())
    assert float((results[0][0].detach() - mft).abs().max() / mft.max()) <= 1e-12


def test_czt_in_float32_matches_the_float64_mft():
    spec = OpticsSpec.with_samples_across(96, focal_n=160)
    ref = OpticalSystem(spec, dtype=torch.float64, method="mft")
    czt = OpticalSystem(spec, dtype=torch.float32, method="czt")
    phase = _phases(ref)["halfring"]
    a, b = ref.psf(phase), czt.psf(phase.float()).double()
    assert float((a - b).abs().max() / a.max()) <= 2e-5
    assert float(b.max()) / ref.uncoded_peak == pytest.approx(float(a.max()) / ref.uncoded_peak, rel=1e-4)


def test_czt_gradcheck():
    spec = OpticsSpec.with_samples_across(12, focal_n=20)
    czt = OpticalSystem(spec, dtype=torch.float64, method="czt")
    g = torch.Generator().manual_seed(5)
    phase = torch.rand(czt.grid.n, czt.grid.n, generator=g, dtype=torch.float64, requires_grad=True)
    weights = torch.rand(20, 20, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda ph: (czt.psf(ph) * weights).sum(), (phase,), eps=1e-6, atol=1e-9)
    mft = OpticalSystem(spec, dtype=torch.float64, method="mft")
    (g_czt,) = torch.autograd.grad((czt.psf(phase) * weights).sum(), phase)
    (g_mft,) = torch.autograd.grad((mft.psf(phase) * weights).sum(), phase)
    torch.testing.assert_close(g_czt, g_mft, rtol=1e-10, atol=1e-14)


# ---- LSR of the uncoded PSF ---------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["mft", "czt", "fft"])
def test_zero_phase_has_unit_lsr(method):
    spec = _native_spec(focal_n=64, fft_n=192) if method == "fft" else OpticsSpec.with_samples_across(S, focal_n=64)
    system = OpticalSystem(spec, dtype=torch.float64, method=method)
    phase = torch.zeros_like(system.grid.aperture)
    psf = system.psf(phase)
    h0 = system.uncoded_peak
    assert float(metrics.lsr_sampled(psf, h0)) == pytest.approx(1.0, abs=1e-6)
    assert system.continuous_peak(phase).value / h0 == pytest.approx(1.0, abs=1e-6)
    assert float(metrics.lsr_smooth(psf, h0, p=1e4)) == pytest.approx(1.0, abs=1e-3)


def test_zero_phase_unit_lsr_float32():
    spec = OpticsSpec.with_samples_across(S, focal_n=64)
    system = OpticalSystem(spec, dtype=torch.float32)
    psf = system.uncoded_psf()
    assert float(metrics.lsr_sampled(psf, system.uncoded_peak)) == pytest.approx(1.0, abs=1e-5)
    assert system.continuous_peak(torch.zeros_like(system.grid.aperture)).value / system.uncoded_peak == \
        pytest.approx(1.0, abs=1e-5)


def test_halfring_lowers_lsr(small_system64):
    phase = _phases(small_system64)["halfring"]
    psf = small_system64.psf(phase)
    h0 = small_system64.uncoded_peak
    refined = small_system64.continuous_peak(phase).value / h0
    sampled = float(metrics.lsr_sampled(psf, h0))
    assert 0 < sampled <= refined < 0.1
    assert refined <= sampled * 1.5


# ---- tilt ---------------------------------------------------------------------------------------------------
def _subpixel_peak(psf: torch.Tensor) -> tuple[float, float]:
    m = psf.shape[-1]
    iy, ix = divmod(int(psf.argmax()), m)

    def vertex(a, b, c):
        la, lb, lc = math.log(a), math.log(b), math.log(c)
        return 0.5 * (la - lc) / (la - 2 * lb + lc)

    dy = vertex(*(float(psf[iy + k, ix]) for k in (-1, 0, 1)))
    dx = vertex(*(float(psf[iy, ix + k]) for k in (-1, 0, 1)))
    return iy - m // 2 + dy, ix - m // 2 + dx


TILT_METHODS, TILT_AXES, TILT_SHIFTS_PX = ["mft", "fft"], ["x", "y"], [10.3, -7.6, 0.45]
TILT_TOL_PX = 0.05  # |sub-pixel peak position - f alpha / dx|


def _tilted(method: str, axis: str, shift_px: float):
    """(system, tilt phase, PSF, sub-pixel peak offset along the tilt, along the other axis, expected offset)."""
    spec = _native_spec(focal_n=64, fft_n=192) if method == "fft" else OpticsSpec.with_samples_across(S, focal_n=64)
    system = OpticalSystem(spec, dtype=torch.float64, method=method)
    g = system.grid
    alpha = shift_px * spec.focal_pitch_m / spec.focal_length_m  # tilt angle [rad]
    k = 2 * math.pi * alpha / spec.wavelength_m
    if axis == "x":
        phase = k * g.u[None, :].expand(g.n, g.n)  # u varies along columns
    else:
        phase = k * g.v[:, None].expand(g.n, g.n)  # v varies along rows
    psf = system.psf(phase)
    py, px = _subpixel_peak(psf)
    moved, still = (px, py) if axis == "x" else (py, px)
    x_expected = spec.focal_length_m * alpha / spec.focal_pitch_m  # = shift_px
    return system, phase, psf, moved, still, x_expected


def tilt_error(method: str, axis: str, shift_px: float, tilted: tuple | None = None) -> float:
    """|sub-pixel peak position - f alpha / dx| [px] of the PSF of a pupil tilted by alpha (``tilted``: the
    _tilted result of these arguments, computed when not given)."""
    _, _, _, moved, _, x_expected = _tilted(method, axis, shift_px) if tilted is None else tilted
    return abs(moved - x_expected)


@pytest.mark.parametrize("method", TILT_METHODS)
@pytest.mark.parametrize("axis", TILT_AXES)
@pytest.mark.parametrize("shift_px", TILT_SHIFTS_PX)
def test_tilt_moves_peak_to_f_alpha(method, axis, shift_px):
    tilted = _tilted(method, axis, shift_px)
    system, phase, psf, moved, still, x_expected = tilted
    assert abs(moved - x_expected) <= 1.0
    assert tilt_error(method, axis, shift_px, tilted) <= TILT_TOL_PX  # sub-pixel estimate (measured ~0.004 px)
    assert abs(still) <= 1e-6
    # a tilt is lossless: the continuous peak stays h0(0)
    assert system.continuous_peak(phase).value / system.uncoded_peak == pytest.approx(1.0, abs=2e-3)


# ---- MTF ----------------------------------------------------------------------------------------------------
MTF_AUTOCORRELATION_ATOL = 1e-12  # max |MTF - normalized pupil autocorrelation|


def _mtf_and_autocorrelation() -> tuple[torch.Tensor, torch.Tensor]:
    """(2-D MTF of the uncoded PSF on one replica period at the native pitch, normalized pupil autocorrelation)."""
    m, samples = 128, 48
    spec = _native_spec(focal_n=m, fft_n=m, samples=samples)
    system = OpticalSystem(spec, dtype=torch.float64, method="mft")
    mtf2d = metrics.mtf(system.uncoded_psf())
    a = system.grid.aperture
    padded = torch.zeros(m, m, dtype=torch.float64)
    padded[: a.shape[0], : a.shape[1]] = a
    ac = torch.fft.ifft2(torch.fft.fft2(padded).abs() ** 2).real
    return mtf2d, ac.abs() / ac[0, 0]


def mtf_autocorrelation_error(pair: tuple[torch.Tensor, torch.Tensor] | None = None) -> float:
    """max |uncoded MTF - |pupil autocorrelation| / its value at 0| (what assert_close(rtol=0, atol) bounds)."""
    mtf2d, ref = _mtf_and_autocorrelation() if pair is None else pair
    return float((mtf2d - ref).abs().max())


def test_uncoded_mtf_is_exact_pupil_autocorrelation():
    # window = one replica period at the native pitch: the window DFT of the PSF is exactly the (zero-padded)
    # autocorrelation of the pupil amplitude
    mtf2d, ref = _mtf_and_autocorrelation()
    assert mtf2d.shape == ref.shape and mtf2d.dtype == ref.dtype == torch.float64
    assert mtf_autocorrelation_error((mtf2d, ref)) <= MTF_AUTOCORRELATION_ATOL  # a NaN fails too


# hard edge (P = 1000): measured max |error| 1.8e-3; the paper's P = 50 edge lifts the MTF by up to 0.012 at low
# frequencies (independent of window and sampling: the analytic curve is for a hard edge)
RADIAL_MTF_TOL = {1000.0: 5e-3, 50.0: 1.5e-2}  # edge order P -> max |radial MTF - circular-pupil MTF|, nu < 0.95


def _radial_mtf(order: float):
    """(radial MTF of the uncoded PSF with super-Gaussian edge order P, its frequencies in units of the cutoff)."""
    spec = OpticsSpec.with_samples_across(80, focal_n=256, supergaussian_order=order)
    system = OpticalSystem(spec, dtype=torch.float64)
    radial = RadialMTF(spec)
    return radial(metrics.mtf(system.uncoded_psf())), radial.freqs


def _radial_mtf_errors(order: float):
    """(radial MTF, its frequencies, the selection 0 < nu < 0.95, |radial MTF - circular-pupil MTF| there)."""
    rad, f = _radial_mtf(order)
    sel = (f > 0) & (f < 0.95)
    return rad, f, sel, (rad - circular_mtf(f))[sel].abs()


def radial_mtf_error(order: float) -> float:
    """max |radial MTF - circular-pupil MTF| over 0 < nu < 0.95."""
    return float(_radial_mtf_errors(order)[3].max())


@pytest.mark.parametrize("order", list(RADIAL_MTF_TOL))
def test_uncoded_radial_mtf_matches_circular_pupil(order):
    rad, f, sel, err = _radial_mtf_errors(order)
    assert int(sel.sum()) >= 60
    assert float(err.max()) <= RADIAL_MTF_TOL[order], \
        f"max |MTF - circular| = {float(err.max()):.4f} at nu = {float(f[sel][err.argmax()]):.3f}"
    assert float(rad[0]) == pytest.approx(1.0, abs=1e-12)
    assert float(rad[f > 1.02].abs().max()) <= 1e-3  # nothing beyond the incoherent cutoff


def test_circular_mtf_values():
    nu = torch.tensor([0.0, 0.5, 1.0, 1.5], dtype=torch.float64)
    got = circular_mtf(nu)
    expected = (2 / math.pi) * (math.acos(0.5) - 0.5 * math.sqrt(0.75))
    torch.testing.assert_close(got, torch.tensor([1.0, expected, 0.0, 0.0], dtype=torch.float64))


def test_fft_propagator_on_default_optics_matches_mft():
    # conf/optics/default.yaml with optics.propagator=fft (fft_n = null): what a user gets from
    # `python -m codesign +experiment=psf optics.propagator=fft`
    spec = OpticsSpec(pupil_pitch_m=9.974e-6, focal_n=640, propagator="fft")
    mft = OpticalSystem(spec, dtype=torch.float32, method="mft")
    fft = OpticalSystem(spec, dtype=torch.float32)
    assert fft.method == "fft"
    phase = published_halfring(mft.grid, spec.aperture_diameter_m).phase().detach()
    lsr_mft = float(metrics.lsr_sampled(mft.psf(phase), mft.uncoded_peak))
    lsr_fft = float(metrics.lsr_sampled(fft.psf(phase), fft.uncoded_peak))
    assert lsr_fft == pytest.approx(lsr_mft, rel=0.05), (
        f"sampled LSR via FFT (fft_n = {fft.propagator.fft_n}, native pitch {fft.propagator.native_pitch:.4g} m "
        f"for a {spec.focal_pitch_m:.4g} m window) = {lsr_fft:.5f}, via MFT = {lsr_mft:.5f}")


@pytest.mark.slow
def test_default_sampling_lsr_within_one_percent_of_paper_sampling():
    # conf/optics/default.yaml: 384 samples across is "the coarsest sampling whose LSR is within 1 % of the
    # converged float64 value"; compare with Table 1's 1024 samples across (float64, exact MFT)
    lsr = {}
    for pitch in (9.974e-6, 3.74e-6):
        spec = OpticsSpec(pupil_pitch_m=pitch, propagator="mft")
        system = OpticalSystem(spec, dtype=torch.float64)
        phase = published_halfring(system.grid, spec.aperture_diameter_m).phase().detach()
        lsr[pitch] = system.continuous_peak(phase).value / system.uncoded_peak
    assert lsr[9.974e-6] == pytest.approx(lsr[3.74e-6], rel=1e-2)  # measured -0.13 %
    assert 0.005 < lsr[3.74e-6] < 0.02
