"""TensorBoard monitoring of a mask: LSR / MTF scalars, per-ring parameters, histograms, phase / PSF / MTF images
and the radial-MTF curve against a reference (the published mask). Shared by psf, joint and mask_search.

"""
from __future__ import annotations

import math

import numpy as np

from codesign.design.merit import mask_figures_of_merit
from codesign.io import plots
from codesign.optics import RadialMTF, build_mask
from codesign.optics.masks import published_mask_config


def published_reference(mask_cfg: dict, system):
    """The frozen published mask on ``system``'s grid, under the configured conventions: every comparison's baseline."""
    return build_mask(published_mask_config(mask_cfg), system.grid, system.spec.aperture_diameter_m).freeze()


def _unit(img: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return np.clip((img - lo) / (hi - lo), 0, 1)[None].astype(np.float32)


class MaskMonitor:
    """Logs a mask's figures of merit and pictures to a SummaryWriter, against a reference mask.

    Args:
        system: OpticalSystem; reference: the published mask (or None); band: MTF summary band (normalized
        frequency); p: the smooth-LSR exponent.
    """

    def __init__(self, system, reference=None, band: tuple[float, float] = (0.0, 0.5), p: float = 16.0):
        self.system, self.band, self.p = system, tuple(band), p
        self.radial = RadialMTF(system.spec, device=system.grid.rho.device)
        self.reference = None
        if reference is not None:
            self.reference = mask_figures_of_merit(system, reference, self.radial, self.band, p)

    def measure(self, mask, refine: bool = False) -> tuple[dict, dict]:
        return mask_figures_of_merit(self.system, mask, self.radial, self.band, self.p, refine)

    def log(self, writer, step: int, mask, images: bool = True, prefix: str = "mask") -> dict:
        """Scalars (and, when ``images``, pictures and histograms) of ``mask`` at ``step``; returns the scalars."""
        values, arrays = self.measure(mask)
        if writer is None:
            return values
        for k, v in values.items():
            writer.add_scalar(f"{prefix}/{k}", v, step)
        for k, v in mask.summary().items():
            writer.add_scalar(f"{prefix}_params/{k}", v, step)
        if self.reference is not None:
            ref = self.reference[0]
            writer.add_scalar(f"{prefix}/lsr_smooth_vs_published", values["lsr_smooth"] / ref["lsr_smooth"], step)
            writer.add_scalar(f"{prefix}/mtf_mean_vs_published", values["mtf_mean"] / ref["mtf_mean"], step)
        if images:
            self._images(writer, step, mask, arrays, prefix)
        writer.flush()
        return values

    def _images(self, writer, step: int, mask, arrays: dict, prefix: str) -> None:
        for name, p in mask.named_parameters():
            writer.add_histogram(f"{prefix}_params/{name}", p.detach().cpu(), step)
        ap = self.system.grid.aperture.cpu().numpy() > 1e-3
        phase = np.where(ap, arrays["phase"].cpu().numpy(), -math.pi)
        writer.add_image(f"{prefix}/phase", _unit(phase, -math.pi, math.pi), step)
        psf = arrays["psf"].cpu().numpy()
        top = math.log10(self.system.uncoded_peak)
        writer.add_image(f"{prefix}/psf_log10", _unit(np.log10(np.maximum(psf, 1e-30)), top - 7, top), step)
        writer.add_image(f"{prefix}/mtf2d_log10", _unit(np.log10(np.maximum(arrays["mtf2d"].cpu().numpy(), 1e-5)),
                                                        -4, 0), step)
        freqs = self.radial.freqs.cpu().numpy()
        curves = {"this mask": arrays["mtf_radial"].cpu().numpy()}
        if self.reference is not None:
            curves["published mask"] = self.reference[1]["mtf_radial"].cpu().numpy()
        fig = plots.mtf_figure(freqs, curves, self.band, f"radial MTF at step {step}")
        writer.add_figure(f"{prefix}/mtf_curve", fig, step, close=True)
