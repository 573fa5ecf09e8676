"""A measured PSF against the design's (``optics.psf_file``): the figures of merit every experiment that takes one
reports, and the figure simulate draws.

LSR: the window PSF's peak sample / h0(0), the design optical system's uncoded peak (``system.uncoded_peak``), for
both the measured and the design PSF on the same window (so both are sampled LSRs, ``lsr_sampled`` elsewhere, not
the certified continuous peak of ``lsr``). mtf_mean: the radial MTF of the window PSF (normalized to 1 at zero
frequency) averaged over ``metrics.mtf_band``, as for every mask.

Physics guard: no phase mask makes an LSR above 1 (h0(0) is the most light any mask puts on a point) or an MTF above
the aperture's diffraction-limited one (|OTF| <= OTF0 for every pupil phase). A measured PSF on the window that does
(a frame coarser than the window, resampled; the files' own check, codesign/optics/measured.diffraction_check,
refuses the grosser cases before any work) is warned about, naming the pitch, the energy and the file, and
``measured_psf_physical`` is false in metrics.json.
"""
from __future__ import annotations

import numpy as np
import torch

from codesign.errors import ConfigError
from codesign.optics import RadialMTF, metrics
from codesign.optics.measured import PEAK_TOLERANCE

CENTRES = {"design": "design PSF's centroid", "centroid": "optical axis", "frame": "axis (frame centre)"}
MTF_TOLERANCE = 0.02  # relative: a measured mtf_mean this far above the uncoded one's is beyond diffraction


def _figures(psf: torch.Tensor, h0: float, radial: RadialMTF, band) -> tuple[float, float, np.ndarray]:
    p = psf.detach().to(torch.float64).cpu()
    rad = radial(metrics.mtf(p))
    return float(p.max()) / h0, float(radial.summary(rad, band)[0]), rad.numpy()


@torch.no_grad()
def measured_psf_report(camera, band: tuple[float, float], log, curves: dict | None = None) -> dict:
    """The metrics.json entries of a camera's measured PSF (nothing without one): its path and processing, its LSR
    and mtf_mean beside the design mask's over the MTF band ``band`` (metrics.mtf_band), and ``laser_halo`` False;
    one log line compares them. ``curves``: a dict that receives what ``measured_psf_figure`` draws."""
    if camera.measured is None:
        return {}
    m = camera.measured
    state = camera.frozen_optics().state  # places the measured PSF (camera.placement, camera.design_psf)
    spec, h0 = camera.system.spec, camera.system.uncoded_peak
    radial = RadialMTF(spec)
    lsr, mtf_mean, rad = _figures(state.psf, h0, radial, band)
    design_lsr, design_mtf, design_rad = _figures(camera.design_psf, h0, radial, band)
    placed = camera.placement
    if not float(state.psf.sum()) > 0:  # every figure would be 0 / 0
        raise ConfigError("optics.psf_file", m.path, f"none of its light falls on the {spec.focal_n} x {spec.focal_n} "
                          f"optics window ({spec.focal_extent_m:.3g} m, shifted by {placed.shift} px of "
                          f"optics.psf_pitch_m = {m.pitch_m:g} m onto the {CENTRES[m.centre]}): check "
                          "optics.psf_pitch_m, optics.psf_centre and the file")
    if m.clip_warning():
        log.warning(m.clip_warning())
    limit_mtf = _figures(camera.system.uncoded_psf(), h0, radial, band)[1]  # the aperture's diffraction limit
    physical = lsr <= 1 + PEAK_TOLERANCE and mtf_mean <= limit_mtf * (1 + MTF_TOLERANCE)
    if not physical:
        log.warning(_beyond_diffraction(m, spec, lsr, mtf_mean, limit_mtf))
    log.info("measured PSF %s: LSR %.3g (design %s mask %.3g: %.2fx), mtf_mean %.4f (design %.4f: %+.1f%%); "
             "shifted by (%d, %d) px of %.3g m onto the %s; %.2f%% of its light beyond the window", m.path, lsr,
             camera.mask.kind, design_lsr, lsr / design_lsr, mtf_mean, design_mtf, 100 * (mtf_mean / design_mtf - 1),
             placed.shift[0], placed.shift[1], m.pitch_m, CENTRES[m.centre], 100 * placed.outside)
    if curves is not None:
        curves.update(measured=state.psf.detach().cpu().numpy(), design=camera.design_psf.cpu().numpy(),
                      freqs=radial.freqs.numpy(), mtf_measured=rad, mtf_design=design_rad, band=band,
                      pitch_m=spec.focal_pitch_m, h0=h0)
    return {"measured_psf": m.path, "measured_psf_dark": m.dark_path, "measured_psf_pitch_m": m.pitch_m,
            "measured_psf_frame_px": [int(m.shape[0]), int(m.shape[1])], "measured_psf_energy": m.energy,
            "measured_psf_centre": m.centre, "measured_psf_shift_px": [int(placed.shift[0]), int(placed.shift[1])],
            "measured_psf_outside_window": placed.outside, "measured_psf_clipped_samples": m.clipped,
            "measured_psf_clipped_light": m.clipped_light, "measured_psf_physical": physical,
            "diffraction_mtf_mean": limit_mtf,
            "measured_psf_window_energy": float(state.psf.sum()), "measured_lsr": lsr, "measured_mtf_mean": mtf_mean,
            "design_lsr": design_lsr, "design_mtf_mean": design_mtf, "design_window_energy":
                float(camera.design_psf.sum()), "laser_halo": False}


def _beyond_diffraction(m, spec, lsr: float, mtf_mean: float, limit_mtf: float) -> str:
    """The warning of a measured window PSF beyond the diffraction limit (LSR above 1 or mtf_mean above the
    uncoded one's), naming what sets its scale: the file, its pitch and its energy."""
    found = []
    if lsr > 1 + PEAK_TOLERANCE:
        found.append(f"LSR {lsr:.3g} > 1")
    if mtf_mean > limit_mtf * (1 + MTF_TOLERANCE):
        found.append(f"mtf_mean {mtf_mean:.4f} > {limit_mtf:.4f}, the diffraction limit (the uncoded aperture's)")
    coarse = "; the frame is coarser than the window and was interpolated" if m.pitch_m > spec.focal_pitch_m else ""
    return (f"measured PSF {m.path}: on the {spec.focal_n} x {spec.focal_n} window of {spec.focal_pitch_m:g} m its "
            f"{' and '.join(found)}: no mask can do this, so these figures are not the optics': the frame is narrower "
            f"than diffraction at optics.psf_pitch_m = {m.pitch_m:g} m (check the file's pixel pitch at the sensor "
            f"plane, optics.psf_energy = {m.energy:g} and the file{coarse})")


def measured_psf_figure(curves: dict, title: str):
    """The design and the measured window PSF (log scale, one colour scale) and their radial MTFs."""
    from codesign.io.plots import log_psf_panel, mtf_panel, plt, window_extent_mm

    design, measured = curves["design"], curves["measured"]
    ext = window_extent_mm(design.shape[0], curves["pitch_m"])
    vmax = np.log10(max(float(design.max()), float(measured.max())))
    fig, axes = plt.subplots(1, 3, figsize=(16.5, 4.6))
    for ax, img, name in ((axes[0], design, "design (computed)"), (axes[1], measured, "measured")):
        log_psf_panel(fig, ax, img, ext, vmax, f"{name}: LSR {float(img.max()) / curves['h0']:.3g}")
    mtf_panel(axes[2], curves["freqs"], {"design": curves["mtf_design"], "measured": curves["mtf_measured"]},
              curves["band"], "MTF")
    fig.suptitle(title)
    fig.tight_layout()
    return fig
