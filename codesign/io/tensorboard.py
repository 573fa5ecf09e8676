"""TensorBoard writers of a run directory: every experiment writes its events into its own run directory, so
``tensorboard --logdir outputs`` lists all runs side by side."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from codesign.config.runtime import logging_spec


def tensorboard_enabled(cfg) -> bool:
    """``logging.tensorboard`` of a composed config (the LoggingSpec default when the block is absent)."""
    return logging_spec(cfg).tensorboard


def open_writer(run_dir: Path, enabled: bool = True, purge_step: int | None = None):
    """A SummaryWriter on ``run_dir`` (None when ``enabled`` is false)."""
    if not enabled:
        return None
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(log_dir=str(run_dir), purge_step=purge_step or None)


def log_summary(writer, hparams: dict, metrics: dict, prefix: str = "final") -> None:
    """Every scalar of a run's metrics.json as ``prefix/<key>`` at step 0, plus the hparams table; closes the
    writer. Non-scalar entries (tables, lists) stay in metrics.json."""
    if writer is None:
        return
    scalars = {k: float(v) for k, v in metrics.items()
               if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))}
    for k, v in scalars.items():
        writer.add_scalar(f"{prefix}/{k}", v, 0)
    hp = {k: (v if isinstance(v, (int, float, str, bool)) else str(v)) for k, v in hparams.items()}
    writer.add_hparams(hp, {f"hparam/{k}": v for k, v in scalars.items()}, run_name="hparams")
    writer.close()


def _unit(img: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return np.clip((img - lo) / (hi - lo), 0, 1)[None].astype(np.float32)


def log_mask(writer, step: int, mask, values: dict, arrays: dict, *, reference: tuple | None, aperture: np.ndarray,
             uncoded_peak: float, freqs: np.ndarray, band: tuple[float, float], images: bool = True,
             prefix: str = "mask") -> None:
    """A mask's figures of merit at ``step``: the scalars ``values`` (and their ratios to ``reference``'s, the
    published mask's (values, arrays)), its parameters, and, when ``images``, histograms of its parameters, its
    phase, log PSF and log MTF as images and its radial MTF against the reference's. ``arrays``: phase (n, n),
    psf (m, m), mtf2d (m, m), mtf_radial (bins,) tensors; ``aperture``: the pupil transmission (n, n);
    ``uncoded_peak``: h0(0), the top of the PSF's log scale; ``freqs``: the radial MTF's frequencies."""
    from codesign.io import plots

    for k, v in values.items():
        writer.add_scalar(f"{prefix}/{k}", v, step)
    for k, v in mask.summary().items():
        writer.add_scalar(f"{prefix}_params/{k}", v, step)
    if reference is not None:
        ref = reference[0]
        writer.add_scalar(f"{prefix}/lsr_smooth_vs_published", values["lsr_smooth"] / ref["lsr_smooth"], step)
        writer.add_scalar(f"{prefix}/mtf_mean_vs_published", values["mtf_mean"] / ref["mtf_mean"], step)
    if images:
        for name, p in mask.named_parameters():
            writer.add_histogram(f"{prefix}_params/{name}", p.detach().cpu(), step)
        phase = np.where(aperture > 1e-3, arrays["phase"].cpu().numpy(), -math.pi)
        writer.add_image(f"{prefix}/phase", _unit(phase, -math.pi, math.pi), step)
        top = math.log10(uncoded_peak)
        psf = arrays["psf"].cpu().numpy()
        writer.add_image(f"{prefix}/psf_log10", _unit(np.log10(np.maximum(psf, 1e-30)), top - 7, top), step)
        mtf2d = arrays["mtf2d"].cpu().numpy()
        writer.add_image(f"{prefix}/mtf2d_log10", _unit(np.log10(np.maximum(mtf2d, 1e-5)), -4, 0), step)
        curves = {"this mask": arrays["mtf_radial"].cpu().numpy()}
        if reference is not None:
            curves["published mask"] = reference[1]["mtf_radial"].cpu().numpy()
        fig = plots.mtf_figure(freqs, curves, band, f"radial MTF at step {step}")
        writer.add_figure(f"{prefix}/mtf_curve", fig, step, close=True)
    writer.flush()
