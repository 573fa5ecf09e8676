"""Figures of the optics: phase map, PSF on a log scale, radial and 2-D MTF."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")  # headless: runs write PNGs, never open windows
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def window_extent_mm(m: int, pitch_m: float) -> np.ndarray:
    """imshow extent [mm] of an m x m focal window (or pupil grid) at ``pitch_m``, centred on the axis."""
    return np.array([-m / 2, m / 2, -m / 2, m / 2]) * pitch_m * 1e3


def phase_figure(phase: np.ndarray, aperture: np.ndarray, pitch_m: float, title: str):
    """The pupil phase [rad] on the aperture (NaN outside), axes in mm from ``pitch_m`` [m]."""
    ext = window_extent_mm(phase.shape[0], pitch_m)
    shown = np.where(aperture > 1e-3, phase, np.nan)
    fig, ax = plt.subplots(figsize=(5, 4.2))
    im = ax.imshow(shown, cmap="twilight", extent=ext, origin="lower", vmin=-np.pi, vmax=np.pi)
    fig.colorbar(im, ax=ax, label="phase [rad]")
    ax.set(xlabel="u [mm]", ylabel="v [mm]", title=title)
    return fig


def log_psf_panel(fig, ax, img: np.ndarray, extent: np.ndarray, vmax: float, title: str) -> None:
    """A PSF on a log scale over the seven decades below 10^vmax, with its colour bar."""
    im = ax.imshow(np.log10(np.maximum(img, 10.0 ** (vmax - 7))), cmap="inferno", extent=extent, origin="lower",
                   vmin=vmax - 7, vmax=vmax)
    ax.set(xlabel="x [mm]", ylabel="y [mm]", title=title)
    fig.colorbar(im, ax=ax, label="log10 energy per pixel")


def mtf_panel(ax, freqs: np.ndarray, curves: dict[str, np.ndarray], band: tuple[float, float], title: str,
              dashed: tuple[str, ...] = ("analytic",), legend_size=None) -> None:
    """Radial MTFs (name -> curve; dashed where the name holds one of ``dashed``) on a log axis, the summary band
    shaded."""
    for name, y in curves.items():
        ax.plot(freqs, y, "--" if any(d in name for d in dashed) else "-", label=name)
    ax.axvspan(band[0], band[1], color="0.9", zorder=0, label="summary band")
    ax.set(xlim=(0, 1.05), ylim=(1e-4, 1.05), yscale="log", xlabel="normalized frequency nu / (W_a / lambda f)",
           ylabel="radial mean MTF", title=title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=legend_size)


def psf_figure(psf: np.ndarray, psf0: np.ndarray, pitch_m: float, title: str):
    """The uncoded and the coded PSF side by side, on the same log scale (seven decades below h0's peak)."""
    ext = window_extent_mm(psf.shape[0], pitch_m)
    vmax = np.log10(float(psf0.max()))
    # constrained layout: each colour bar and its label keep clear of the next panel's axis labels
    fig, axes = plt.subplots(1, 2, figsize=(10.5, 4.4), layout="constrained")
    for ax, img, name in ((axes[0], psf0, "uncoded h0"), (axes[1], psf, "coded h")):
        log_psf_panel(fig, ax, img, ext, vmax, name)
    fig.suptitle(title)
    return fig


def mtf_figure(freqs: np.ndarray, curves: dict[str, np.ndarray], band: tuple[float, float], title: str):
    """Radial MTF curves (name -> values at ``freqs``, normalized to the cutoff) with the summary ``band`` shaded."""
    fig, ax = plt.subplots(figsize=(6, 4))
    mtf_panel(ax, freqs, curves, band, title)
    return fig


def mtf2d_figure(mtf2d_shifted: np.ndarray, freq_step_norm: float, title: str):
    """The 2-D MTF (DC centred) in log10, axes in units of the cutoff (``freq_step_norm``: one bin's step)."""
    m = mtf2d_shifted.shape[0]
    ext = np.array([-m / 2, m / 2, -m / 2, m / 2]) * freq_step_norm
    fig, ax = plt.subplots(figsize=(5, 4.2))
    im = ax.imshow(np.log10(np.maximum(mtf2d_shifted, 1e-5)), cmap="viridis", extent=ext, origin="lower",
                   vmin=-4, vmax=0)
    ax.set(xlim=(-1.1, 1.1), ylim=(-1.1, 1.1), xlabel="nu_x / cutoff", ylabel="nu_y / cutoff", title=title)
    fig.colorbar(im, ax=ax, label="log10 MTF")
    return fig
