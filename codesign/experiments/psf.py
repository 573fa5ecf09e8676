"""``+experiment=psf``: the configured mask's phase, PSF, LSR/BSR and MTF, with timings, arrays and figures."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from codesign.config.runtime import resolve_dtype, tensorboard_enabled
from codesign.design.check import sampling_report
from codesign.optics.metrics import require_band_frequencies
from codesign.design.limits import MTFLimit
from codesign.design.merit import (MaskMonitor, MetricsSpec, evaluate_mask, published_reference,
                                   time_forward_backward)
from codesign.optics.masks.records import write_record
from codesign.errors import require_number
from codesign.fab.laser_lines import lines_summary, log_lines, lsr_curve, lsr_wavelength_figure, run_lines, surface_name
from codesign.io import files as io
from codesign.io import plots
from codesign.io.tensorboard import log_summary, open_writer
from codesign.optics import OpticalSystem, OpticsSpec, build_mask, circular_mtf
from codesign.experiments.specs import material_of, metrics_spec
from codesign.experiments.protocol import Experiment

log = logging.getLogger("codesign.psf")


EXPERIMENT = Experiment(
    summary="PSF, LSR, BSR and MTF of a mask against the physical limit: figures, arrays, metrics.json",
    first_work="time_forward_backward",
    root_keys=("precision", "timing_repeats"),
    reads=("optics", "material", "mask", "metrics"),
    outputs=("metrics.json", "mask.json", "phase.png", "psf_log.png", "mtf.png", "mtf2d.png"),
    smoke={"timing_repeats": 1},
)


def run(cfg: DictConfig, run_dir: Path, device: torch.device) -> float:
    """The configured mask on its optics: its figures of merit (LSR sampled, smooth and certified, BSR, MTF) timed
    through the differentiable chain, against the physical limit, with its phase/PSF/MTF figures and arrays, its
    laser lines when configured, mask.json and metrics.json; returns its LSR. Steps: settings, build, measure,
    figures, laser lines, report."""
    s = _settings(cfg)
    system = OpticalSystem(s.spec, dtype=s.dtype, device=device)
    mask = build_mask(s.mask_cfg, system.grid, s.spec.aperture_diameter_m)
    values, arrays, metrics_out = _measure(s, system, mask, device)
    label = f"{s.mask_cfg['kind']} ({metrics_out['phase_convention']})"
    _figures(run_dir, s, system, arrays, values, label)
    lines = run_lines(material_of(cfg), system)
    if lines is not None:
        metrics_out["laser_lines"] = _laser_lines(cfg, run_dir, s, system, lines, mask, label)
    _report(cfg, run_dir, s, system, mask, values, metrics_out)
    return values["lsr"]


@dataclass(frozen=True)
class _Settings:
    """The run's settings, every one checked before any work."""

    spec: OpticsSpec
    dtype: torch.dtype
    ms: MetricsSpec
    repeats: int
    mask_cfg: dict


def _settings(cfg: DictConfig) -> _Settings:
    """optics, precision, metrics, timing_repeats and mask of ``cfg``, checked (every MTF figure needs a frequency
    in the band: checked too)."""
    spec = OpticsSpec.from_config(OmegaConf.to_container(cfg.optics, resolve=True))
    dtype = resolve_dtype("precision", cfg.get("precision"))
    ms = metrics_spec(cfg)
    repeats = require_number("timing_repeats", cfg.get("timing_repeats"), lo=1, hi=1000, integer=True)
    mask_cfg = OmegaConf.to_container(cfg.mask, resolve=True)
    require_band_frequencies(spec, ms.mtf_band)  # before any work: every MTF figure needs a frequency in the band
    return _Settings(spec, dtype, ms, repeats, mask_cfg)


def _measure(s: _Settings, system, mask, device) -> tuple[dict, dict, dict]:
    """The chain timed (forward, backward), every figure of merit, the limit at its mtf_mean and the phase
    sampling: (figures, arrays, metrics.json's entries)."""
    spec, band, p = s.spec, s.ms.mtf_band, s.ms.lsr_p
    log.info("pupil %d x %d at %.3g m (%.1f samples across W_a), window %d at %.3g m, propagator %s, %s",
             spec.grid_n, spec.grid_n, spec.pupil_pitch_m, spec.samples_across_aperture, spec.focal_n,
             spec.focal_pitch_m, system.method, s.dtype)
    t_fwd, t_bwd = time_forward_backward(system, mask, p, s.repeats)
    values, arrays = evaluate_mask(system, mask, band, p, s.ms.lsr_grids)
    limit = MTFLimit(system, band)
    values["lsr_limit"] = limit.lsr_limit(values["mtf_mean"], values["psf_energy_in_window"])
    values["lsr_over_limit"] = values["lsr"] / values["lsr_limit"]
    sampling = sampling_report(mask, spec, band, log, f"{s.mask_cfg['kind']} mask", s.dtype)
    metrics_out = {
        **values, **sampling,
        "pupil_n": spec.grid_n, "pupil_pitch_m": spec.pupil_pitch_m,
        "pupil_samples_across_aperture": spec.samples_across_aperture,
        "focal_pitch_m": spec.focal_pitch_m, "focal_n": spec.focal_n,
        "samples_per_lambda_f_over_d": spec.samples_per_lambda_f_over_d,
        "wavelength_m": spec.wavelength_m, "focal_length_m": spec.focal_length_m,
        "aperture_diameter_m": spec.aperture_diameter_m, "propagator": system.method,
        "phase_convention": getattr(mask, "convention", "freeform"), "mask_kind": s.mask_cfg["kind"],
        "precision": str(s.dtype).replace("torch.", ""), "device": str(device), "threads": torch.get_num_threads(),
        "seconds_forward": t_fwd, "seconds_backward": t_bwd, "timing_repeats": s.repeats,
        **mask.summary(),
    }
    if hasattr(mask, "orders"):
        metrics_out["m_o_min"], metrics_out["m_o_max"] = int(mask.orders[0]), int(mask.orders[-1])
    return values, arrays, metrics_out


def _figures(run_dir: Path, s: _Settings, system, arrays: dict, values: dict, label: str) -> None:
    """The arrays (.npy) and the phase, PSF, radial and 2-D MTF figures."""
    spec, band = s.spec, s.ms.mtf_band
    for name, arr in arrays.items():
        io.save_npy(run_dir / f"{name}.npy", arr)
    np_ = {k: v.detach().cpu().numpy() for k, v in arrays.items()}
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


def _laser_lines(cfg: DictConfig, run_dir: Path, s: _Settings, system, lines, mask, label: str) -> dict:
    """The mask at every laser line (metrics.json's laser_lines, with the LSR-against-wavelength curve) and
    lsr_wavelength.png."""
    spec = s.spec
    phase, material = mask.phase().detach(), material_of(cfg)
    summary = lines_summary(lines, {"mask": phase}, mask.plate_cell_m)
    log_lines(summary, "mask", f"{s.mask_cfg['kind']} mask")
    curve = lsr_curve(system, material, lambda ls: [ls.phase(phase, i) for i in range(len(ls))], mask.plate_cell_m)
    summary["curve"] = curve
    io.save_figure(run_dir / "lsr_wavelength.png", lsr_wavelength_figure(
        {f"{label}, {surface_name(lines.wrap)}": curve}, spec.wavelength_m, lines.wavelengths,
        f"LSR against the laser's wavelength: {label} made for {spec.wavelength_m * 1e9:.0f} nm in "
        f"{material.name}"))
    return summary


def _report(cfg: DictConfig, run_dir: Path, s: _Settings, system, mask, values: dict, metrics_out: dict) -> None:
    """mask.json, metrics.json, the TensorBoard events (the mask against the published one, the summary) and the
    log line."""
    spec, band, p = s.spec, s.ms.mtf_band, s.ms.lsr_p
    write_record(run_dir / "mask.json", mask, spec, {**{k: values[k] for k in (
        "lsr", "lsr_smooth", "lsr_sampled", "mtf_mean", "lsr_limit", "lsr_over_limit")},
        "phase_resolved": metrics_out["phase_resolved"]})
    io.write_json(run_dir / "metrics.json", metrics_out)
    writer = open_writer(run_dir, tensorboard_enabled(cfg))
    if writer is not None:
        MaskMonitor(system, published_reference(s.mask_cfg, system), band, p, s.ms.lsr_grids).log(
            writer, 0, mask, images=True, params=False)
    log_summary(writer, {"mask": s.mask_cfg["kind"], "propagator": system.method, "pupil_n": spec.grid_n},
                metrics_out, settings=mask.summary())  # the configured mask's parameters: settings, not measurements
    log.info("lsr=%.4g (the true peak between focal samples; at the samples alone %.4g; the smooth p-norm the "
             "optimizers use %.4g) bsr=%.4f mtf_mean=%.4g mtf_min=%.4g energy_in_window=%.4f "
             "forward %.3f s backward %.3f s", values["lsr"], values["lsr_sampled"], values["lsr_smooth"],
             values["bsr"], values["mtf_mean"], values["mtf_min"], values["psf_energy_in_window"],
             metrics_out["seconds_forward"], metrics_out["seconds_backward"])
    log.info("wrote %s", run_dir)
