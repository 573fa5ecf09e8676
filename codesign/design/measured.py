"""A measured PSF against the design's (``optics.psf_file``): the figures of merit every experiment that takes one
reports, and the figure simulate draws.

LSR: the window PSF's peak sample / h0(0), the design optical system's uncoded peak (``system.uncoded_peak``), for
both the measured and the design PSF on the same window (so both are sampled LSRs, ``lsr_sampled`` elsewhere, not
the refined continuous peak of ``lsr``). mtf_mean: the radial MTF of the window PSF (normalized to 1 at zero
frequency) averaged over ``metrics.mtf_band``, as for every mask.
"""
from __future__ import annotations

import numpy as np
import torch

from codesign.optics import RadialMTF, metrics


def _figures(psf: torch.Tensor, h0: float, radial: RadialMTF, band) -> tuple[float, float, np.ndarray]:
    p = psf.detach().to(torch.float64).cpu()
    rad = radial(metrics.mtf(p))
    return float(p.max()) / h0, float(radial.summary(rad, band)[0]), rad.numpy()


@torch.no_grad()
def measured_psf_report(camera, cfg, log, curves: dict | None = None) -> dict:
    """The metrics.json entries of a camera's measured PSF (nothing without one): its path and processing, its LSR
    and mtf_mean beside the design mask's, and ``laser_halo`` False; one log line compares them. ``curves``: a dict
    that receives what ``measured_psf_figure`` draws."""
    if camera.measured is None:
        return {}
    from codesign.design.merit import metrics_spec

    m = camera.measured
    state = camera.frozen_optics().state  # places the measured PSF (camera.placement, camera.design_psf)
    spec, h0, band = camera.system.spec, camera.system.uncoded_peak, metrics_spec(cfg).mtf_band
    radial = RadialMTF(spec)
    lsr, mtf_mean, rad = _figures(state.psf, h0, radial, band)
    design_lsr, design_mtf, design_rad = _figures(camera.design_psf, h0, radial, band)
    placed = camera.placement
    log.info("measured PSF %s: LSR %.3g (design %s mask %.3g: %.2fx), mtf_mean %.4f (design %.4f: %+.1f%%); "
             "shifted by (%d, %d) px of %.3g m onto the %s; %.2f%% of its light beyond the window", m.path, lsr,
             camera.mask.kind, design_lsr, lsr / design_lsr, mtf_mean, design_mtf, 100 * (mtf_mean / design_mtf - 1),
             placed.shift[0], placed.shift[1], m.pitch_m,
             {"design": "design PSF's centroid", "centroid": "optical axis", "frame": "axis (frame centre)"}[m.centre],
             100 * placed.outside)
    if curves is not None:
        curves.update(measured=state.psf.detach().cpu().numpy(), design=camera.design_psf.cpu().numpy(),
                      freqs=radial.freqs.numpy(), mtf_measured=rad, mtf_design=design_rad, band=band,
                      pitch_m=spec.focal_pitch_m, h0=h0)
    return {"measured_psf": m.path, "measured_psf_dark": m.dark_path, "measured_psf_pitch_m": m.pitch_m,
            "measured_psf_frame_px": [int(m.shape[0]), int(m.shape[1])], "measured_psf_energy": m.energy,
            "measured_psf_centre": m.centre, "measured_psf_shift_px": [int(placed.shift[0]), int(placed.shift[1])],
            "measured_psf_outside_window": placed.outside, "measured_psf_clipped_samples": m.clipped,
            "measured_psf_window_energy": float(state.psf.sum()), "measured_lsr": lsr, "measured_mtf_mean": mtf_mean,
            "design_lsr": design_lsr, "design_mtf_mean": design_mtf, "design_window_energy":
                float(camera.design_psf.sum()), "laser_halo": False}


def measured_psf_figure(curves: dict, title: str):
    """The design and the measured window PSF (log scale, one colour scale) and their radial MTFs."""
    from codesign.io.plots import plt

    design, measured, pitch = curves["design"], curves["measured"], curves["pitch_m"]
    m = design.shape[0]
    ext = np.array([-m / 2, m / 2, -m / 2, m / 2]) * pitch * 1e3
    vmax = np.log10(max(float(design.max()), float(measured.max())))
    fig, axes = plt.subplots(1, 3, figsize=(16.5, 4.6))
    for ax, img, name in ((axes[0], design, "design (computed)"), (axes[1], measured, "measured")):
        im = ax.imshow(np.log10(np.maximum(img, 10 ** (vmax - 7))), cmap="inferno", extent=ext, origin="lower",
                       vmin=vmax - 7, vmax=vmax)
        ax.set(xlabel="x [mm]", ylabel="y [mm]", title=f"{name}: LSR {float(img.max()) / curves['h0']:.3g}")
        fig.colorbar(im, ax=ax, label="log10 energy per pixel")
    ax = axes[2]
    ax.plot(curves["freqs"], curves["mtf_design"], label="design")
    ax.plot(curves["freqs"], curves["mtf_measured"], label="measured")
    ax.axvspan(*curves["band"], color="0.9", zorder=0, label="summary band")
    ax.set(xlim=(0, 1.05), ylim=(1e-4, 1.05), yscale="log", xlabel="normalized frequency nu / (W_a / lambda f)",
           ylabel="radial mean MTF", title="MTF")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.suptitle(title)
    fig.tight_layout()
    return fig
