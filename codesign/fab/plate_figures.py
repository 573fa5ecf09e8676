"""Figures of a fabricated plate: height map, a profile, and its PSF and MTF next to the ideal design's; and the
tolerance analysis's LSR distributions per error source."""
from __future__ import annotations

import numpy as np

from codesign.io.plots import log_psf_panel, mtf_panel, plt, window_extent_mm


def export_figure(height: np.ndarray, inside: np.ndarray, pitch_m: float, psfs: dict[str, np.ndarray],
                  focal_pitch_m: float, mtf: dict[str, np.ndarray], freqs: np.ndarray, band: tuple[float, float],
                  phase_error: np.ndarray, pupil_pitch_m: float, title: str):
    """Top: height map [um], its central row and column over the central fifth, the radial MTFs; bottom: the two
    PSFs (log) of ``psfs`` (name -> (m, m)) and the exported minus the ideal phase on the pupil grid (wrapped,
    NaN outside the aperture)."""
    n = height.shape[0]
    ext = window_extent_mm(n, pitch_m)
    fig, axes = plt.subplots(2, 3, figsize=(15, 8.4))
    ax = axes[0, 0]
    im = ax.imshow(np.where(inside, height * 1e6, np.nan), cmap="viridis", extent=ext, origin="lower",
                   interpolation="nearest")
    fig.colorbar(im, ax=ax, label="height [um]")
    ax.set(xlabel="u [mm]", ylabel="v [mm]", title="surface height")
    ax = axes[0, 1]
    coords = (np.arange(n) - n // 2) * pitch_m * 1e3
    c, k = n // 2, max(n // 10, 2)
    part = slice(c - k, c + k + 1)
    ax.step(coords[part], np.where(inside[c], height[c], np.nan)[part] * 1e6, where="mid", lw=0.8, label="row v = 0")
    ax.step(coords[part], np.where(inside[:, c], height[:, c], np.nan)[part] * 1e6, where="mid", lw=0.8,
            label="column u = 0")
    ax.set(xlabel="position [mm]", ylabel="height [um]", title="profiles through the axis (central fifth)")
    ax.legend()
    mtf_panel(axes[0, 2], freqs, mtf, band, "MTF", dashed=("uncoded",), legend_size=8)
    names = list(psfs)
    fext = window_extent_mm(psfs[names[0]].shape[0], focal_pitch_m)
    vmax = np.log10(max(float(p.max()) for p in psfs.values()))
    for ax, name in zip(axes[1], names):
        log_psf_panel(fig, ax, psfs[name], fext, vmax, name)
    ax = axes[1, 2]
    im = ax.imshow(phase_error, cmap="twilight_shifted", extent=window_extent_mm(phase_error.shape[0], pupil_pitch_m),
                   origin="lower", vmin=-np.pi, vmax=np.pi, interpolation="nearest")
    fig.colorbar(im, ax=ax, label="phase [rad]")
    ax.set(xlabel="u [mm]", ylabel="v [mm]", title="exported - ideal phase (pupil grid)")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


# how each error source's 1-sigma reads on the tolerance figure: (scale, unit) of ToleranceSpec's value
SIGMA_UNITS = {"depth_scale": (100.0, "% of the depth"), "level_noise": (1e9, "nm"), "shift": (1e6, "um per axis"),
               "rotation": (1.0, "deg"), "wavelength": (1e9, "nm"), "defocus": (1e6, "um of sensor travel")}


def sigma_text(source: str, sigma: float) -> str:
    """"sigma 10 nm": an error source's 1-sigma in its unit (SIGMA_UNITS)."""
    scale, unit = SIGMA_UNITS.get(source, (1.0, ""))
    return f"sigma {sigma * scale:.3g} {unit}".rstrip()


def tolerance_figure(lsr: dict[str, np.ndarray], nominal: float, ceiling: float, title: str,
                     sigmas: dict[str, str] | None = None, ceiling_rule: str | None = None):
    """Histogram of the LSR of the Monte Carlo samples of each error source (name -> (N,)), with the nominal
    design's LSR and the yield ceiling. ``sigmas``: name -> the source's 1-sigma as text (sigma_text), in each
    panel's title; ``ceiling_rule``: how the ceiling was set ("1.2 x the nominal LSR"), in the legend."""
    names = list(lsr)
    sigmas = sigmas or {}
    cols = 3
    rows = -(-len(names) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.5 * rows + 0.3), squeeze=False)
    hi = max(float(np.max(v)) for v in lsr.values())
    lo = min(float(np.min(v)) for v in lsr.values())
    bins = np.linspace(min(lo, nominal) * 0.98, max(hi, ceiling) * 1.02, 40)
    for ax, name in zip(axes.flat, names):
        v = lsr[name]
        ax.hist(v, bins=bins, color="C0", alpha=0.8, label="Monte Carlo samples")
        ax.axvline(nominal, color="k", lw=1, label=f"nominal design: {nominal:.4g}")
        rule = f" = {ceiling_rule}" if ceiling_rule else ""
        ax.axvline(ceiling, color="C3", lw=1, ls="--", label=f"yield ceiling{rule}: {ceiling:.4g}")
        head = f"{name} ({sigmas[name]})" if name in sigmas else name
        ax.set_title(f"{head}\nyield (LSR <= ceiling) {np.mean(v <= ceiling):.1%}", fontsize=9)
        ax.set(xlabel="LSR (sampled peak / uncoded peak)", ylabel="samples")
    axes.flat[0].legend(fontsize=7)
    for ax in list(axes.flat)[len(names):]:
        ax.axis("off")
    fig.suptitle(title)
    fig.tight_layout()
    return fig
