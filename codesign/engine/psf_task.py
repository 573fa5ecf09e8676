"""``+experiment=psf``: the configured mask's phase, PSF, LSR/BSR and MTF, with timings, arrays and figures."""
from __future__ import annotations

import logging
import statistics
import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from codesign.config import resolve_dtype
from codesign.engine import io, plots
from codesign.engine.monitor import (MaskMonitor, log_summary, mask_figures_of_merit, open_writer,
                                     published_reference, tensorboard_enabled)
from codesign.errors import ConfigError, require_list, require_number
from codesign.optics import OpticalSystem, OpticsSpec, RadialMTF, build_mask, circular_mtf, metrics

log = logging.getLogger("codesign.psf")


def time_forward_backward(system: OpticalSystem, mask, p: float, repeats: int) -> tuple[float, float]:
    """Median seconds of (mask params -> phase -> PSF -> smooth LSR) and of its backward, after one warm-up."""
    def once() -> tuple[float, float]:
        mask.zero_grad(set_to_none=True)
        sync = torch.cuda.synchronize if system.grid.rho.is_cuda else (lambda: None)
        sync()
        t0 = time.perf_counter()
        loss = metrics.lsr_smooth(system.psf(mask.phase()), system.uncoded_peak, p)
        sync()
        t1 = time.perf_counter()
        if loss.requires_grad:
            loss.backward()
        sync()
        return t1 - t0, time.perf_counter() - t1

    once()
    runs = [once() for _ in range(repeats)]
    return statistics.median(r[0] for r in runs), statistics.median(r[1] for r in runs)


def evaluate_mask(system: OpticalSystem, mask, band: tuple[float, float], p: float) -> tuple[dict, dict]:
    """All figures of merit of a mask on a system; returns (flat metrics, arrays for saving/plotting)."""
    radial = RadialMTF(system.spec, device=system.grid.rho.device)
    values, arr = mask_figures_of_merit(system, mask, radial, band, p, refine=True)
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


def run_psf(cfg: DictConfig, run_dir: Path, device: torch.device) -> float:
    spec = OpticsSpec.from_config(OmegaConf.to_container(cfg.optics, resolve=True))
    dtype = resolve_dtype("precision", cfg.get("precision", "float32"))
    band_allowed = ("must be [low, high] with 0 <= low < high <= 1 (frequency normalized to the incoherent cutoff, "
                    "beyond which the MTF is 0)")
    band = tuple(require_list("mtf_band", cfg.get("mtf_band", (0.0, 0.5)), band_allowed))
    if len(band) != 2 or not 0 <= require_number("mtf_band[0]", band[0]) < require_number("mtf_band[1]", band[1]) \
            or band[1] > 1:
        raise ConfigError("mtf_band", list(band), band_allowed)
    p = require_number("lsr_smooth_p", cfg.get("lsr_smooth_p", 16), lo=1, hi=1024)
    repeats = require_number("timing_repeats", cfg.get("timing_repeats", 5), lo=1, hi=1000, integer=True)
    mask_cfg = OmegaConf.to_container(cfg.mask, resolve=True)

    system = OpticalSystem(spec, dtype=dtype, device=device)
    mask = build_mask(mask_cfg, system.grid, spec.aperture_diameter_m)
    log.info("pupil %d x %d at %.3g m (%.1f samples across W_a), window %d at %.3g m, propagator %s, %s",
             spec.grid_n, spec.grid_n, spec.pupil_pitch_m, spec.samples_across_aperture, spec.focal_n,
             spec.focal_pitch_m, system.method, dtype)
    t_fwd, t_bwd = time_forward_backward(system, mask, p, repeats)
    values, arrays = evaluate_mask(system, mask, band, p)
    metrics_out = {
        **values,
        "pupil_n": spec.grid_n, "pupil_pitch_m": spec.pupil_pitch_m,
        "pupil_samples_across_aperture": spec.samples_across_aperture,
        "focal_pitch_m": spec.focal_pitch_m, "focal_n": spec.focal_n,
        "samples_per_lambda_f_over_d": spec.samples_per_lambda_f_over_d,
        "wavelength_m": spec.wavelength_m, "focal_length_m": spec.focal_length_m,
        "aperture_diameter_m": spec.aperture_diameter_m, "propagator": system.method,
        "phase_convention": getattr(mask, "convention", "freeform"), "mask_kind": mask_cfg["kind"],
        "precision": str(dtype).replace("torch.", ""), "device": str(device), "threads": torch.get_num_threads(),
        "seconds_forward": t_fwd, "seconds_backward": t_bwd, "timing_repeats": repeats,
        **mask.summary(),
    }
    if hasattr(mask, "orders"):
        metrics_out["m_o_min"], metrics_out["m_o_max"] = int(mask.orders[0]), int(mask.orders[-1])

    for name, arr in arrays.items():
        io.save_npy(run_dir / f"{name}.npy", arr)
    np_ = {k: v.detach().cpu().numpy() for k, v in arrays.items()}
    label = f"{mask_cfg['kind']} ({metrics_out['phase_convention']})"
    io.save_figure(run_dir / "phase.png", plots.phase_figure(
        np_["phase"], system.grid.aperture.cpu().numpy(), spec.pupil_pitch_m, f"pupil phase, {label}"))
    io.save_figure(run_dir / "psf_log.png", plots.psf_figure(
        np_["psf"], np_["psf_uncoded"], spec.focal_pitch_m, f"PSF, LSR = {values['lsr']:.3g}"))
    f, rad, rad0 = np_["mtf_radial"]
    analytic = circular_mtf(torch.from_numpy(f)).numpy()
    io.save_figure(run_dir / "mtf.png", plots.mtf_figure(
        f, {"coded": rad, "uncoded": rad0, "analytic circular pupil": analytic}, band,
        f"MTF, mean over band = {values['mtf_mean']:.3g}"))
    step = 1.0 / (spec.focal_n * spec.focal_pitch_m * spec.cutoff_frequency)
    io.save_figure(run_dir / "mtf2d.png", plots.mtf2d_figure(np_["mtf2d"], step, f"2-D MTF, {label}"))
    io.write_json(run_dir / "metrics.json", metrics_out)
    writer = open_writer(run_dir, tensorboard_enabled(cfg))
    if writer is not None:
        MaskMonitor(system, published_reference(mask_cfg, system), band, p).log(writer, 0, mask, images=True)
    log_summary(writer, {"mask": mask_cfg["kind"], "propagator": system.method, "pupil_n": spec.grid_n}, metrics_out)
    log.info("lsr=%.4g (sampled %.4g, smooth %.4g) bsr=%.4f mtf_mean=%.4g mtf_min=%.4g energy_in_window=%.4f "
             "forward %.3f s backward %.3f s", values["lsr"], values["lsr_sampled"], values["lsr_smooth"],
             values["bsr"], values["mtf_mean"], values["mtf_min"], values["psf_energy_in_window"], t_fwd, t_bwd)
    log.info("wrote %s", run_dir)
    return values["lsr"]
