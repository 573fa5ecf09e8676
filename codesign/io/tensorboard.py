"""TensorBoard writers of a run directory: every experiment writes its events into its own run directory, so
``tensorboard --logdir outputs`` lists all runs side by side."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np


def open_writer(run_dir: Path, enabled: bool = True, purge_step: int | None = None):
    """A SummaryWriter on ``run_dir`` (None when ``enabled`` is false)."""
    if not enabled:
        return None
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(log_dir=str(run_dir), purge_step=purge_step or None)


# metrics.json entries that restate a setting (the grid, the optics, the run's size and threads), not a measurement:
# TensorBoard shows them in the hparams table and the "settings" text, never as scalars
SETTING_KEYS = frozenset({
    "pupil_n", "pupil_pitch_m", "pupil_samples_across_aperture", "focal_n", "focal_pitch_m",
    "samples_per_lambda_f_over_d", "wavelength_m", "focal_length_m", "aperture_diameter_m", "laser_wavelength_m",
    "threads", "timing_repeats", "lsr_smooth_p", "lsr_p", "mtf_band_low", "mtf_band_high", "m_o_min", "m_o_max",
    "batch_size", "image_size", "padded_size", "network_pixel_pitch_m", "sensor_resolution", "scene_size",
    "psf_kernel_size", "scenes", "seed", "steps", "max_evals", "parameters"})


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))


def log_summary(writer, hparams: dict, metrics: dict, prefix: str = "final", settings=()) -> None:
    """The measured scalars of a run's metrics.json as ``prefix/<key>`` at step 0, and the hparams table: ``hparams``
    and the entries that are settings (SETTING_KEYS and ``settings``: numbers the configuration fixed, such as the
    grid or the mask's configured parameters) as its columns, the measured scalars as its metrics; the settings also
    as a "settings" text. Closes the writer. Non-scalar entries (tables, lists) stay in metrics.json."""
    if writer is None:
        return
    is_setting = SETTING_KEYS | set(settings)
    scalars = {k: float(v) for k, v in metrics.items() if _number(v) and k not in is_setting}
    fixed = {k: v for k, v in metrics.items() if k in is_setting and (_number(v) or isinstance(v, (str, bool)))}
    for k, v in scalars.items():
        writer.add_scalar(f"{prefix}/{k}", v, 0)
    hp = {k: (v if isinstance(v, (int, float, str, bool)) else str(v)) for k, v in {**fixed, **hparams}.items()}
    if hp:
        writer.add_text("settings", "\n".join(f"    {k} = {v}" for k, v in sorted(hp.items())), 0)
    writer.add_hparams(hp, {f"hparam/{k}": v for k, v in scalars.items()}, run_name="hparams")
    writer.close()


def _unit(img: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return np.clip((img - lo) / (hi - lo), 0, 1)[None].astype(np.float32)


def log_mask(writer, step: int, mask, values: dict, arrays: dict, *, reference: tuple | None, aperture: np.ndarray,
             uncoded_peak: float, freqs: np.ndarray, band: tuple[float, float], images: bool = True,
             prefix: str = "mask", params: bool = True) -> None:
    """A mask's figures of merit at ``step``: the scalars ``values`` (and their ratios to ``reference``'s, the
    published mask's (values, arrays)), its parameters, and, when ``images``, histograms of its parameters, its
    phase, log PSF and log MTF as images and its radial MTF against the reference's. ``arrays``: phase (n, n),
    psf (m, m), mtf2d (m, m), mtf_radial (bins,) tensors; ``aperture``: the pupil transmission (n, n);
    ``uncoded_peak``: h0(0), the top of the PSF's log scale; ``freqs``: the radial MTF's frequencies."""
    from codesign.io import plots

    for k, v in values.items():
        writer.add_scalar(f"{prefix}/{k}", v, step)
    for k, v in (mask.summary() if params else {}).items():  # params false: they are settings (a fixed mask)
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
