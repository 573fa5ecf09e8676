"""Figures of merit of a mask on an optical system: LSR (sampled, smooth, certified continuous peak), BSR, MTF, the
energy kept in the optics window; and the cost of the differentiable chain behind them."""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field

import torch

from codesign.config.store import register, spec_node
from codesign.errors import ConfigError, require_list, require_number
from codesign.io.tensorboard import log_mask
from codesign.optics import OpticalSystem, RadialMTF, build_mask, metrics
from codesign.optics.lines import smooth_lsr
from codesign.optics.masks import published_mask_config
from codesign.optics.metrics import require_band_frequencies
from codesign.optics.psf import SUBSAMPLE_SHIFTS
from codesign.spec_base import SpecMixin

BAND_ALLOWED = ("must be [low, high] with 0 <= low < high <= 1 (frequency normalized to the incoherent cutoff, "
                "beyond which the MTF is 0)")


@dataclass(frozen=True)
class MetricsSpec(SpecMixin):
    """How every experiment (psf, joint, mask_search) scores a mask. lsr_p: p of the smooth LSR ||h||_p / h0(0)
    (>= the sampled LSR; the differentiable LSR of every objective and constraint); mtf_band: [low, high] of
    normalized frequency (nu / cutoff) over which mtf_mean and mtf_min summarize the radial MTF; recheck_tolerance:
    how far (relative) a design's LSR and mtf_mean, or its gain over the published mask, may move on a pupil grid
    finer by the family's factor and a window that holds its whole PSF and still count as reproduced
    (codesign/design/check.py); lsr_grids: the focal grids the smooth LSR is taken over, 1 (the samples), 2 (and
    the grid offset by half a sample along both axes) or 4 (and along either): so that an optimizer cannot hide a
    peak between the samples (the hard LSR is the certified continuous peak whatever this is)."""

    lsr_p: float = 16.0
    lsr_grids: int = 2
    mtf_band: tuple = (0.0, 0.5)
    recheck_tolerance: float = 0.02
    prefix: str = field(default="metrics", compare=False, repr=False)

    def __post_init__(self) -> None:
        p = self.prefix
        object.__setattr__(self, "lsr_p", require_number(f"{p}.lsr_p", self.lsr_p, lo=1, hi=1024))
        band = require_list(f"{p}.mtf_band", self.mtf_band, BAND_ALLOWED)
        if len(band) != 2 or not 0 <= require_number(f"{p}.mtf_band[0]", band[0]) < \
                require_number(f"{p}.mtf_band[1]", band[1]) <= 1:
            raise ConfigError(f"{p}.mtf_band", list(band), BAND_ALLOWED)
        object.__setattr__(self, "mtf_band", (float(band[0]), float(band[1])))
        require_number(f"{p}.recheck_tolerance", self.recheck_tolerance, lo=0, lo_open=True, hi=1)
        if isinstance(self.lsr_grids, bool) or self.lsr_grids not in SUBSAMPLE_SHIFTS:
            raise ConfigError(f"{p}.lsr_grids", self.lsr_grids, "must be 1, 2 or 4 (the focal grids the smooth LSR "
                              "is taken over: the samples, and the grids offset by half a sample)")
        object.__setattr__(self, "lsr_grids", int(self.lsr_grids))


register("metrics", "default", spec_node(MetricsSpec))


@torch.no_grad()
def mask_figures_of_merit(system, mask, radial: RadialMTF, band: tuple[float, float], p: float,
                          refine: bool = False, grids: int = 1) -> tuple[dict, dict]:
    """(scalars, arrays) of a mask: LSR (sampled, smooth; certified continuous peak when ``refine``), BSR, MTF.

    arrays: phase (n, n), psf (m, m), mtf2d (m, m, DC centred), mtf_radial (n_bins,).
    """
    phase = mask.phase()
    psf = system.psf(phase, mask.plate_cell_m)
    smooth, sampled = (float(v) for v in smooth_lsr(system, phase, psf, p, grids, mask.plate_cell_m))
    mtf2d = metrics.mtf(psf)
    rad = radial(mtf2d)
    mean, mn = radial.summary(rad, band)
    out = {"lsr_sampled": sampled, "lsr_smooth": smooth, "mtf_mean": float(mean), "mtf_min": float(mn),
           "bsr": float(psf.sum()) / system.uncoded_energy}
    if refine:
        out["lsr"] = system.continuous_lsr(phase, mask.plate_cell_m)
        out["lsr_smooth_gap"] = smooth / out["lsr"] - 1
    else:
        out["lsr_smooth_gap"] = smooth / sampled - 1
    arrays = {"phase": phase, "psf": psf, "mtf2d": torch.fft.fftshift(mtf2d), "mtf_radial": rad}
    return out, arrays


def time_forward_backward(system: OpticalSystem, mask, p: float, repeats: int) -> tuple[float, float]:
    """Median seconds of (mask params -> phase -> PSF -> smooth LSR) and of its backward, after one warm-up."""
    def once() -> tuple[float, float]:
        mask.zero_grad(set_to_none=True)
        sync = torch.cuda.synchronize if system.grid.rho.is_cuda else (lambda: None)
        sync()
        t0 = time.perf_counter()
        loss = metrics.lsr_smooth(system.mask_psf(mask), system.uncoded_peak, p)
        sync()
        t1 = time.perf_counter()
        if loss.requires_grad:
            loss.backward()
        sync()
        return t1 - t0, time.perf_counter() - t1

    once()
    runs = [once() for _ in range(repeats)]
    return statistics.median(r[0] for r in runs), statistics.median(r[1] for r in runs)


def evaluate_mask(system: OpticalSystem, mask, band: tuple[float, float], p: float, grids: int = 1
                  ) -> tuple[dict, dict]:
    """All figures of merit of a mask on a system; returns (flat metrics, arrays for saving/plotting)."""
    radial = RadialMTF(system.spec, device=system.grid.rho.device)
    values, arr = mask_figures_of_merit(system, mask, radial, band, p, refine=True, grids=grids)
    with torch.no_grad():
        psf0 = system.uncoded_psf()
        rad0 = radial(metrics.mtf(psf0))
        mean0, mn0 = radial.summary(rad0, band)
    out = {
        **values, "lsr_smooth_p": p, "mtf_mean_uncoded": float(mean0), "mtf_min_uncoded": float(mn0),
        "mtf_band_low": band[0], "mtf_band_high": band[1],
        "psf_energy_in_window": float(arr["psf"].sum()), "psf_uncoded_energy_in_window": float(psf0.sum()),
        "psf_peak": float(arr["psf"].max()), "psf_uncoded_peak": system.uncoded_peak,
    }
    arrays = {"phase": arr["phase"], "psf": arr["psf"], "psf_uncoded": psf0, "mtf2d": arr["mtf2d"],
              "mtf_radial": torch.stack([radial.freqs.to(rad0), arr["mtf_radial"], rad0])}
    return out, arrays


def published_reference(settings: dict, system):
    """The frozen published mask on ``system``'s grid, under the conventions of the mask ``settings`` (the mask
    block, as build_mask takes it): every comparison's baseline."""
    return build_mask(published_mask_config(settings), system.grid, system.spec.aperture_diameter_m).freeze()


class MaskMonitor:
    """A mask's figures of merit on ``system`` against a reference mask (the published one, or None), measured for
    the records and logged to TensorBoard (codesign.io.tensorboard.log_mask). ``band``: the MTF summary band;
    ``p``, ``grids``: the smooth LSR's exponent and focal grids (metrics.lsr_p, metrics.lsr_grids)."""

    def __init__(self, system, reference, band: tuple[float, float], p: float, grids: int = 1):
        require_band_frequencies(system.spec, band)  # a band without a frequency of the window: no MTF to watch
        self.system, self.band, self.p, self.grids = system, tuple(band), p, grids
        self.radial = RadialMTF(system.spec, device=system.grid.rho.device)
        self.reference = None if reference is None else self.measure(reference)

    def measure(self, mask, refine: bool = False) -> tuple[dict, dict]:
        """(scalars, arrays) of ``mask`` (mask_figures_of_merit; ``refine``: the certified continuous peak too)."""
        return mask_figures_of_merit(self.system, mask, self.radial, self.band, self.p, refine, self.grids)

    def log(self, writer, step: int, mask, images: bool = True, prefix: str = "mask", params: bool = True) -> dict:
        """Scalars (and, when ``images``, pictures and histograms) of ``mask`` at ``step``; returns the scalars.
        ``params``: its parameters as scalars too (false where they are the configuration's, not learned)."""
        values, arrays = self.measure(mask)
        if writer is not None:
            log_mask(writer, step, mask, values, arrays, reference=self.reference,
                     aperture=self.system.grid.aperture.cpu().numpy(), uncoded_peak=self.system.uncoded_peak,
                     freqs=self.radial.freqs.cpu().numpy(), band=self.band, images=images, prefix=prefix,
                     params=params)
        return values
