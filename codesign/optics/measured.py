"""A measured PSF in place of the computed one (``optics.psf_file``): read, checked, registered and resampled onto
the optics window.

Input: a 16-bit PNG / TIFF frame (raw counts) or a .npy array of floats, with its pixel pitch at the sensor plane
(``optics.psf_pitch_m``), optionally a dark frame of the same kind and size (``optics.psf_dark_file``). Every way
the files can be wrong is a ConfigError naming the key, the file and what is allowed, raised by ``load_measured``
(which the experiments call before any work): no such file, another format, 8-bit samples, not one 2-D frame, a
frame smaller than MIN_SIDE pixels, saturated samples (65535 in a 16-bit frame: its peak is clipped), NaN or inf,
negative samples beyond rounding in a .npy, a dark frame of another kind or size, no light left after the dark
frame is subtracted, and a frame whose brightest pixel holds more light than diffraction lets into a pixel of its
pitch (``diffraction_check``: a PSF narrower than the aperture's diffraction limit, an LSR above 1, cannot be; the
message gives the pitch and the psf_energy that would make it possible). A missing pitch is refused by OpticsSpec
(``optics.psf_pitch_m``).

Processing (``load_measured``, then ``MeasuredPSF.place`` once the optics window and the design PSF are known):
  1. dark frame  frame - dark, negative samples (noise of an empty background) clipped to 0;
  2. energy      divided by its sum: the frame holds all the light it saw; the light outside the frame is unknown.
                 The frame is then scaled to ``optics.psf_energy`` (default 1): the fraction of all the light through
                 the aperture that the frame holds (the computed window PSF holds psf_energy_in_window < 1 of it);
  3. register    shifted by whole pixels of the file, so that no sample is interpolated, by the rounded distance
                 between its centroid and the target (``optics.psf_centre``): ``design`` (default) the centroid of
                 the design mask's computed window PSF (the optical axis is not marked in a measured frame; the
                 design says where a PSF of this mask lies relative to it: the published mask's centroid lies 34 and
                 23 pixels off the axis on the 640-sample window), ``centroid`` the optical axis, ``frame`` no
                 shift (the file's centre pixel, index (H // 2, W // 2), is the axis);
  4. resample    onto the optics window (optics.focal_n samples at optics.focal_pitch_m, the sensor pitch) by area
                 integration, along rows then columns: the frame's cumulative sums, exact at its pixels' edges,
                 interpolated at the window pixels' edges by a monotone cubic (PCHIP), so that every window pixel
                 gets the light that falls on it, >= 0, and the total is conserved (a linear interpolation of the
                 sums, i.e. each file pixel uniformly lit, errs 100x more on a smooth PSF). At the window's own
                 pitch (within 1e-9 relative) the frame is copied, cropped or zero padded unchanged.
                 Light that falls beyond the window is lost to the window PSF (warned with its fraction): like the
                 light a computed PSF sends beyond the window, the scene's share of it returns as the uniform veil
                 (sensor.background_veil), the laser's is dropped (there is no halo of a measured PSF).
A measured PSF equal to the computed one, i.e. the computed window PSF saved as a .npy at the sensor pitch, read
with ``optics.psf_energy`` = its sum, comes out of these steps as it went in (to float rounding).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from codesign.errors import ConfigError, round_down, round_up, special_file

SIXTEEN_BIT = (".png", ".tif", ".tiff")
SUFFIXES = SIXTEEN_BIT + (".npy",)
MIN_SIDE = 3  # a frame smaller than this is no PSF (nothing to centre, nothing to resample)
SATURATED = 65535  # a 16-bit sample at full scale: the light there was clipped
NEGATIVE_TOLERANCE = 1e-6  # negative .npy samples down to this fraction of the peak are rounding, clipped to 0
SAME_PITCH = 1e-9  # relative: a file pitch this close to the window's is copied, not interpolated
OUTSIDE_WARN = 1e-4  # the fraction of the frame's light beyond the window above which a run warns
# A pixel's share of the light above the diffraction-limited peak x its area by more than this (relative) is refused:
# the bound holds for every phase mask (|E(x)| <= the aberration-free field's peak), so only rounding of the
# aperture's sampled sums and sample noise on a near diffraction-limited frame may exceed it at all.
PEAK_TOLERANCE = 0.01
MIN_ENERGY = 1e-6  # psf_energy below this is no PSF of the aperture, and 1e-300 underflowed float32 to a NaN MTF
CLIP_WARN = 0.01  # the share of the frame's samples clipped below the dark frame above which a run warns
CENTRES = ("design", "centroid", "frame")
# The OpticsSpec keys of a measured PSF and their defaults (a checkpoint written before they existed had these).
MEASURED_DEFAULTS = {"psf_file": None, "psf_pitch_m": None, "psf_dark_file": None, "psf_energy": 1.0,
                     "psf_centre": "design"}
ALLOWED = "a measured PSF is a 16-bit PNG / TIFF frame or a .npy array of floats"


@dataclass
class Placement:
    """A measured PSF on the optics window: psf (m, m) float64, holding ``energy`` x (1 - outside); shift: the
    (rows, columns) shift applied, in file pixels; outside: the fraction of the frame's light beyond the window."""

    psf: np.ndarray
    shift: tuple[int, int]
    outside: float


@dataclass
class MeasuredPSF:
    """A checked measured PSF frame, dark-subtracted and normalized to unit sum (``frame``), with what it came from."""

    path: str
    dark_path: str | None
    pitch_m: float
    energy: float
    centre: str
    frame: np.ndarray
    kind: str
    clipped: int  # samples below the dark frame, clipped to 0
    clipped_light: float = 0.0  # the light the clipping added, as a fraction of the frame's light after it

    @property
    def clipped_share(self) -> float:
        """The fraction of the frame's samples clipped below the dark frame."""
        return self.clipped / self.frame.size

    def clip_warning(self) -> str | None:
        """The console warning of a dark frame that clips more than CLIP_WARN of the samples, else None."""
        if self.dark_path is None or self.clipped_share <= CLIP_WARN:
            return None
        return (f"optics.psf_dark_file '{self.dark_path}': {self.clipped:,} of the {self.frame.size:,} samples of "
                f"optics.psf_file '{self.path}' ({100 * self.clipped_share:.1f}%) lie below it and were clipped to 0, "
                f"which added {100 * self.clipped_light:.2g}% to the frame's light (a dark frame of the same "
                "exposure and gain leaves about half of an empty background's samples below it: its noise; a "
                "brighter one clips the PSF's own light)")

    @property
    def shape(self) -> tuple[int, int]:
        """The frame's (rows, columns)."""
        return self.frame.shape

    def place(self, spec, design_psf: np.ndarray | None = None) -> Placement:
        """The frame registered (``centre``) and resampled onto ``spec``'s optics window, scaled to ``energy``.
        ``design_psf``: the design mask's computed window PSF (m, m), needed by centre = design."""
        p, dx, m = self.pitch_m, spec.focal_pitch_m, spec.focal_n
        shift = registration_shift(self.frame, p, self.centre, design_psf, dx)
        window = resample(self.frame, p, shift, m, dx)
        outside = max(0.0, 1.0 - float(window.sum()))
        return Placement(window * self.energy, shift, outside)


def _read(path: Path, key: str) -> tuple[np.ndarray, str]:
    """(samples as float64, kind) of one file, every format error a ConfigError naming ``key`` and the file."""
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise ConfigError(key, str(path), f"must be a {', '.join(SUFFIXES)} file: {ALLOWED}")
    if not path.is_file():
        kind = "a folder" if path.is_dir() else special_file(path)
        raise ConfigError(key, str(path), f"is {kind}, not a regular file: {ALLOWED}" if kind else "no such file")
    if suffix in SIXTEEN_BIT:
        from codesign.io.captures import read_counts

        try:
            arr = read_counts(path, key)
        except ConfigError as err:
            raise ConfigError(key, str(path), f"{err.allowed}; {ALLOWED}") from None
        saturated = int((arr >= SATURATED).sum())
        if saturated:
            raise ConfigError(key, str(path), f"has {saturated} sample(s) at {SATURATED} (the 16-bit maximum): the "
                              "PSF's peak is clipped, so its shape and LSR would be wrong: take a shorter exposure")
        return arr, "16-bit"
    try:
        raw = np.load(path, allow_pickle=False)
    except Exception as err:  # noqa: BLE001 - any reader failure: say which file
        raise ConfigError(key, str(path), f"cannot be read as a .npy array ({type(err).__name__}: {err})") from None
    if not isinstance(raw, np.ndarray) or raw.dtype.kind not in "fiu":
        what = raw.dtype if isinstance(raw, np.ndarray) else type(raw).__name__
        raise ConfigError(key, str(path), f"holds {what} values: expected real numbers (float or integer samples)")
    if raw.dtype.kind in "iu" and raw.dtype.itemsize == 1:  # as an 8-bit PNG is refused (read_counts)
        raise ConfigError(key, str(path), f"has {raw.dtype} samples: 8-bit integers cannot hold a PSF's range (its "
                          f"peak over its halo); {ALLOWED} (or 16-bit integer counts)")
    if raw.ndim != 2:
        raise ConfigError(key, str(path), f"has shape {raw.shape}: expected one 2-D frame (H, W)")
    if raw.dtype == np.uint16 and (raw == SATURATED).any():
        raise ConfigError(key, str(path), f"has {int((raw == SATURATED).sum())} sample(s) at {SATURATED} (the 16-bit "
                          "maximum): the PSF's peak is clipped, so its shape and LSR would be wrong: take a shorter "
                          "exposure")
    arr = raw.astype(np.float64)
    bad = int((~np.isfinite(arr)).sum())
    if bad:
        raise ConfigError(key, str(path), f"has {bad} non-finite sample(s) (NaN or inf): a PSF holds finite "
                          "energies only")
    peak = float(arr.max(initial=0.0))
    low = float(arr.min(initial=0.0))
    if low < -NEGATIVE_TOLERANCE * peak or (low < 0 and peak <= 0):
        share = f" ({-low / peak:.2g} of its peak)" if peak > 0 else ""
        raise ConfigError(key, str(path), f"has negative samples down to {low:.4g}{share}: light is never negative "
                          f"(rounding down to {NEGATIVE_TOLERANCE:g} of the peak is clipped to 0); save the frame "
                          "before its background was subtracted and give the background as optics.psf_dark_file")
    return arr, ".npy"


def load_measured(spec) -> MeasuredPSF | None:
    """The measured PSF of an OpticsSpec (None when ``psf_file`` is null), its files read and checked: every
    ConfigError before any work. See the module docstring."""
    if spec.psf_file is None:
        return None
    p = spec.prefix
    if spec.psf_energy < MIN_ENERGY:
        raise ConfigError(f"{p}.psf_energy", spec.psf_energy, f"a frame holding less than {MIN_ENERGY:g} of the light "
                          "through the aperture is not its PSF (its samples would underflow the float32 simulation "
                          f"to 0): must be >= {MIN_ENERGY:g} and <= 1")
    path = Path(spec.psf_file).expanduser()
    frame, kind = _read(path, f"{p}.psf_file")
    h, w = frame.shape
    if min(h, w) < MIN_SIDE:
        raise ConfigError(f"{p}.psf_file", str(path), f"is {w} x {h} px: a PSF frame must be at least {MIN_SIDE} x "
                          f"{MIN_SIDE} px")
    clipped, dark_path = 0, None
    if spec.psf_dark_file is not None:
        dark_path = Path(spec.psf_dark_file).expanduser()
        dark, dark_kind = _read(dark_path, f"{p}.psf_dark_file")
        if dark_kind != kind:
            raise ConfigError(f"{p}.psf_dark_file", str(dark_path), f"is a {dark_kind} file, {p}.psf_file "
                              f"'{path}' a {kind} one: the dark frame must be of the same kind and units")
        if dark.shape != frame.shape:
            raise ConfigError(f"{p}.psf_dark_file", str(dark_path), f"is {dark.shape[1]} x {dark.shape[0]} px, "
                              f"{p}.psf_file '{path}' {w} x {h} px: the dark frame must be taken with the same "
                              "camera settings and size")
        frame = frame - dark
        clipped = int((frame < 0).sum())
        below = float(-frame[frame < 0].sum())  # the light the clipping adds (a positive floor of rectified noise)
    frame = np.clip(frame, 0.0, None)  # noise below the dark level, and rounding below 0 of a .npy
    total = float(frame.sum())
    if not total > 0:
        raise ConfigError(f"{p}.psf_file", str(path), "holds no light: every sample is 0" + (
            f" after subtracting {p}.psf_dark_file '{dark_path}' (is it the frame itself?)" if dark_path else ""))
    measured = MeasuredPSF(str(path), None if dark_path is None else str(dark_path), float(spec.psf_pitch_m),
                           float(spec.psf_energy), spec.psf_centre, frame / total, kind, clipped,
                           below / total if clipped else 0.0)
    diffraction_check(measured, spec)
    return measured


def diffraction_peak_m2(spec) -> float:
    """The uncoded PSF's peak irradiance per m^2 at the focal plane for unit energy through the aperture, exact on
    the spec's pupil grid (OpticalSystem.uncoded_peak / focal_pitch_m^2): (sum A)^2 du^2 / ((lambda f)^2 sum A^2).
    No phase mask puts more light on any point (|E(x)| <= sum |A| = the uncoded field on the axis)."""
    import torch

    from codesign.optics.grid import supergaussian_aperture

    # the aperture of PupilGrid.from_spec (integer offsets, zero beyond the support), without its polar tables
    k = torch.arange(spec.grid_n, dtype=torch.int64) - spec.grid_n // 2
    r2 = k[:, None] ** 2 + k[None, :] ** 2
    inside = r2 <= (spec.aperture_support_radius_m / spec.pupil_pitch_m) ** 2
    a = supergaussian_aperture(torch.sqrt(r2[inside].to(torch.float64)) * spec.pupil_pitch_m,
                               spec.aperture_diameter_m, spec.supergaussian_order)
    return float(a.sum() ** 2 / (a**2).sum()) * (spec.pupil_pitch_m / spec.lambda_f) ** 2


def diffraction_check(m: MeasuredPSF, spec) -> None:
    """Refuse a frame whose brightest pixel holds more light than the diffraction-limited peak of the aperture puts
    into a pixel of its pitch (an LSR above 1 at the file's pitch: a delta, a hot pixel, a pitch given too small or
    psf_energy too large). The light a pixel of side p receives is at most I0 p^2 (``diffraction_peak_m2``)."""
    p = spec.prefix
    share, peak_m2 = float(m.frame.max()) * m.energy, diffraction_peak_m2(spec)
    bound = peak_m2 * m.pitch_m**2
    if share <= bound * (1 + PEAK_TOLERANCE):
        return
    lsr = share / bound
    need_pitch = round_up(math.sqrt(share / peak_m2))
    most_energy = round_down(bound / float(m.frame.max()))
    limit = (f"{100 * round_down(bound):.3g}%: the diffraction-limited peak of the "
             f"{spec.aperture_diameter_m * 1e3:g} mm aperture at {p}.wavelength_m = {spec.wavelength_m:g}, "
             f"f = {spec.focal_length_m:g} m")
    raise ConfigError(f"{p}.psf_file", m.path, f"its brightest pixel holds {100 * share:.3g}% of the light "
                      f"({p}.psf_energy = {m.energy:g}), {lsr:.3g}x the most any mask can put into one pixel of "
                      f"{p}.psf_pitch_m = {m.pitch_m:g} m ({limit}): a PSF narrower than diffraction (LSR "
                      f"{lsr:.3g} > 1) cannot be; possible with {p}.psf_pitch_m >= {need_pitch:.3g} m or "
                      f"{p}.psf_energy <= {most_energy:.3g}, or a frame of these optics without a hot pixel")


def centroid_px(values: np.ndarray) -> tuple[float, float]:
    """(row, column) centroid of a non-negative (H, W) array in pixels from its centre sample (H // 2, W // 2), the
    sample that lies on the optical axis (codesign.optics.grid.axis_coords)."""
    v = np.asarray(values, dtype=np.float64)
    total = v.sum()
    rows = np.arange(v.shape[0]) - v.shape[0] // 2
    cols = np.arange(v.shape[1]) - v.shape[1] // 2
    return float(v.sum(1) @ rows / total), float(v.sum(0) @ cols / total)


def registration_shift(frame: np.ndarray, pitch_m: float, centre: str, design_psf: np.ndarray | None,
                       window_pitch_m: float) -> tuple[int, int]:
    """Whole file pixels (rows, columns) to shift the frame by (see the module docstring, step 3)."""
    if centre == "frame":
        return 0, 0
    if centre == "design":
        if design_psf is None:
            raise ValueError("centre = design needs the design mask's window PSF")
        target = [c * window_pitch_m / pitch_m for c in centroid_px(design_psf)]
    else:
        target = [0.0, 0.0]
    here = centroid_px(frame)
    return tuple(int(math.floor(t - c + 0.5)) for t, c in zip(target, here))


def integrate_axis(values: np.ndarray, pitch_in: float, start_m: float, n_out: int, pitch_out: float,
                   axis: int) -> np.ndarray:
    """``values`` (non-negative energies per input pixel) integrated over the output pixels along ``axis``: input
    pixel j spans start_m + j pitch_in +- pitch_in / 2, output pixel i (i - n_out // 2) pitch_out +- pitch_out / 2.
    The cumulative sum at the input pixels' edges (exact) is interpolated at the output pixels' edges by a monotone
    cubic (PCHIP), so every output is >= 0 and the output holds exactly the light of the input that falls within it
    (all of it when the output covers the input); a piecewise-linear interpolation of the cumulative sum (each input
    pixel uniformly lit) errs 100x more on a smooth PSF (tests/optics/test_measured_psf.py)."""
    from scipy.interpolate import PchipInterpolator

    n_in = values.shape[axis]
    edges_in = start_m + (np.arange(n_in + 1) - 0.5) * pitch_in
    cum = np.cumsum(values, axis=axis)
    cum = np.concatenate([np.zeros_like(np.take(cum, [0], axis=axis)), cum], axis=axis)
    edges_out = np.clip((np.arange(n_out + 1) - n_out // 2 - 0.5) * pitch_out, edges_in[0], edges_in[-1])
    return np.clip(np.diff(PchipInterpolator(edges_in, cum, axis=axis)(edges_out), axis=axis), 0.0, None)


# Input pixels kept beyond the window's edge on each side: PCHIP's slope at a node depends on the two intervals
# beside it and its end slopes on the first two, so the window's pixels are those of the whole frame.
_MARGIN = 4


def resample(frame: np.ndarray, pitch_in: float, shift: tuple[int, int], n_out: int, pitch_out: float) -> np.ndarray:
    """The (H, W) frame at ``pitch_in``, shifted by ``shift`` input pixels, on the (n_out, n_out) window at
    ``pitch_out`` (both centred on the axis, sample n // 2): a copy / crop / zero pad at equal pitch (within
    SAME_PITCH), else area integration (``integrate_axis`` along rows, then columns) of the part of the frame that
    can reach the window."""
    h, w = frame.shape
    if abs(pitch_in - pitch_out) <= SAME_PITCH * pitch_out:
        out = np.zeros((n_out, n_out), dtype=np.float64)
        r0 = n_out // 2 - h // 2 + shift[0]  # window row of the frame's first row
        c0 = n_out // 2 - w // 2 + shift[1]
        rs, re = max(r0, 0), min(r0 + h, n_out)
        cs, ce = max(c0, 0), min(c0 + w, n_out)
        if rs < re and cs < ce:
            out[rs:re, cs:ce] = frame[rs - r0:re - r0, cs - c0:ce - c0]
        return out
    lo, hi = (-(n_out // 2) - 0.5) * pitch_out, (n_out - n_out // 2 - 0.5) * pitch_out  # the window's extent
    spans, starts = [], []
    for n, s in ((h, shift[0]), (w, shift[1])):
        first = (s - n // 2) * pitch_in  # centre of input pixel 0
        a = max(0, math.floor((lo - first) / pitch_in) - _MARGIN)
        b = min(n, math.ceil((hi - first) / pitch_in) + 1 + _MARGIN)
        if a >= b:  # the frame lies beyond the window
            return np.zeros((n_out, n_out), dtype=np.float64)
        spans.append(slice(a, b))
        starts.append(first + a * pitch_in)
    part = frame[spans[0], spans[1]]
    rows = integrate_axis(part, pitch_in, starts[0], n_out, pitch_out, 0)
    return integrate_axis(rows, pitch_in, starts[1], n_out, pitch_out, 1)
