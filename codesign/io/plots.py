"""Figures of the optics: phase map, PSF on a log scale, radial and 2-D MTF."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")  # headless: runs write PNGs, never open windows
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def phase_figure(phase: np.ndarray, aperture: np.ndarray, pitch_m: float, title: str):
    n = phase.shape[0]
    ext = np.array([-n / 2, n / 2, -n / 2, n / 2]) * pitch_m * 1e3
    shown = np.where(aperture > 1e-3, phase, np.nan)
    fig, ax = plt.subplots(figsize=(5, 4.2))
    im = ax.imshow(shown, cmap="twilight", extent=ext, origin="lower", vmin=-np.pi, vmax=np.pi)
    fig.colorbar(im, ax=ax, label="phase [rad]")
    ax.set(xlabel="u [mm]", ylabel="v [mm]", title=title)
    return fig


def psf_figure(psf: np.ndarray, psf0: np.ndarray, pitch_m: float, title: str):
    m = psf.shape[0]
    ext = np.array([-m / 2, m / 2, -m / 2, m / 2]) * pitch_m * 1e3
    floor = max(float(psf0.max()) * 1e-9, 1e-30)
    vmax = np.log10(float(psf0.max()))
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    for ax, img, name in ((axes[0], psf0, "uncoded h0"), (axes[1], psf, "coded h")):
        im = ax.imshow(np.log10(np.maximum(img, floor)), cmap="inferno", extent=ext, origin="lower",
                       vmin=vmax - 7, vmax=vmax)
        ax.set(xlabel="x [mm]", ylabel="y [mm]", title=name)
        fig.colorbar(im, ax=ax, label="log10 energy per pixel")
    fig.suptitle(title)
    return fig


def mtf_figure(freqs: np.ndarray, curves: dict[str, np.ndarray], band: tuple[float, float], title: str):
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, y in curves.items():
        style = "--" if "analytic" in name else "-"
        ax.plot(freqs, y, style, label=name)
    ax.axvspan(band[0], band[1], color="0.9", zorder=0, label="summary band")
    ax.set(xlim=(0, 1.05), ylim=(1e-4, 1.05), yscale="log", xlabel="normalized frequency nu / (W_a / lambda f)",
           ylabel="radial mean MTF", title=title)
    ax.grid(alpha=0.3)
    ax.legend()
    return fig


def mtf2d_figure(mtf2d_shifted: np.ndarray, freq_step_norm: float, title: str):
    m = mtf2d_shifted.shape[0]
    ext = np.array([-m / 2, m / 2, -m / 2, m / 2]) * freq_step_norm
    fig, ax = plt.subplots(figsize=(5, 4.2))
    im = ax.imshow(np.log10(np.maximum(mtf2d_shifted, 1e-5)), cmap="viridis", extent=ext, origin="lower",
                   vmin=-4, vmax=0)
    ax.set(xlim=(-1.1, 1.1), ylim=(-1.1, 1.1), xlabel="nu_x / cutoff", ylabel="nu_y / cutoff", title=title)
    fig.colorbar(im, ax=ax, label="log10 MTF")
    return fig
