"""``+experiment=export mask.init=PATH``: a design (any family's record, or the configured mask such as the
published preset) as a fabrication file: the wrapped phase as surface heights in ``material`` at the design
wavelength, quantized to ``export.levels`` when set, on the ``export.pitch_m`` grid; and the design as exported,
seen again by the pupil grid, scored against the ideal design (LSR, mtf_mean, the MTF limit, restorability)."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from codesign.camera import build_sensor_spec
from codesign.data.scenes import build_scene_source
from codesign.design.limits import MTFLimit
from codesign.design.merit import evaluate_mask
from codesign.design.search_setup import restorability_tools
from codesign.fab.laser_lines import (lines_summary, log_lines, lsr_curve, lsr_wavelength_figure, run_lines,
                                      surface_name)
from codesign.fab.plate_setup import build_plate, plate_sidecar
from codesign.fab.plate_figures import export_figure
from codesign.fab.surface import PlatePhase
from codesign.fab.writers import write_height_png, write_height_tiff
from codesign.io import files as io
from codesign.optics import OpticalSystem, build_mask
from codesign.experiments.specs import metrics_spec, plate_settings
from codesign.experiments.protocol import Experiment

log = logging.getLogger("codesign.export")


EXPERIMENT = Experiment(
    summary="a design as surface heights in a material, K levels, on a fabrication grid",
    first_work="OpticalSystem",
    root_keys=("precision", "export"),
    reads=("optics", "material", "mask", "sensor", "data", "metrics"),
    outputs=("metrics.json", "export.json", "height_m.npy", "height.png", "height.tif", "report.png"),
    smoke={"export.pitch_m": 8.0e-6},  # a 490 x 490 plate
)

# the figures of the ideal and the exported design that metrics.json holds, each as ideal_* and exported_*
FIGURES = ("lsr", "lsr_sampled", "mtf_mean", "psf_energy_in_window", "lsr_limit", "lsr_over_limit",
           "restorability")


def phase_difference(phase: torch.Tensor, reference: torch.Tensor, aperture: torch.Tensor) -> np.ndarray:
    """phase - reference wrapped into [-pi, pi), NaN outside the aperture (for the report); a uniform offset (the
    piston of a continuous surface that starts from its lowest point) taken out first."""
    raw = phase.double() - reference.double()
    inside = aperture > 0
    piston = torch.angle(torch.exp(1j * raw[inside]).mean()) if bool(inside.any()) else 0.0
    d = torch.remainder(raw - piston + torch.pi, 2 * torch.pi) - torch.pi
    return torch.where(aperture > 0, d, torch.full_like(d, float("nan"))).cpu().numpy()


def _line_outputs(run_dir: Path, metrics: dict, system, lines, mask, plate, material, kind: str, dtype) -> None:
    """The ideal design and the exported plate at every laser line (metrics.json: laser_lines) and the LSR against
    wavelength of both (lsr_wavelength.png): the plate's heights seen at each line, quantization included."""
    def plate_phases(ls):
        return [plate.pupil_phase(sy.grid, sy.spec.wavelength_m, material.index(sy.spec.wavelength_m), dtype=dtype)
                for sy in ls.systems]

    ideal = mask.phase().detach()
    summary = lines_summary(lines, {"ideal": ideal}, mask.plate_cell_m)
    summary.update({k: v for k, v in lines_summary(lines, {"exported": plate_phases(lines)}).items()
                    if k == "exported"})
    metrics["laser_lines"] = summary
    for name in ("ideal", "exported"):
        log_lines(summary, name, f"{name} {kind} design")
    made = f"{plate.n_levels} levels" if plate.n_levels else "continuous heights"
    curves = {f"ideal design ({surface_name(lines.wrap)})": lsr_curve(
        system, material, lambda ls: [ls.phase(ideal, i) for i in range(len(ls))], mask.plate_cell_m),
        f"exported plate ({made})": lsr_curve(system, material, plate_phases)}
    summary["curves"] = curves
    io.save_figure(run_dir / "lsr_wavelength.png", lsr_wavelength_figure(
        curves, system.spec.wavelength_m, lines.wavelengths, f"{kind} plate in {material.name}, made for "
        f"{system.spec.wavelength_m * 1e9:.0f} nm: LSR against the laser's wavelength"))


def run(cfg: DictConfig, run_dir: Path, device: torch.device) -> float:
    """The design as a plate (heights in the material, quantized to export.levels, on the export.pitch_m grid),
    the ideal design and the plate seen again by the pupil grid scored side by side (and at every laser line when
    configured); writes the height files, export.json, report.png and metrics.json; returns the exported plate's
    LSR. Steps: build, score, write the plate, report."""
    spec, ex, material, mask_cfg, dtype = plate_settings(cfg)
    ms = metrics_spec(cfg)
    material.check_wavelength(spec.wavelength_m)
    system = OpticalSystem(spec, dtype=dtype, device=device)
    mask = build_mask(mask_cfg, system.grid, spec.aperture_diameter_m).freeze()
    log.info("design: %s mask%s; plate %d x %d at %.3g m in %s (n = %.5f at %.4g nm), %s",
             mask_cfg["kind"], f" from {mask_cfg['init']}" if mask_cfg.get("init") else "", ex.plate_n(spec),
             ex.plate_n(spec), ex.pitch_m, material.name, material.index(spec.wavelength_m), spec.wavelength_m * 1e9,
             f"{ex.levels} levels" if ex.levels else "continuous heights")
    plate = build_plate(mask_cfg, spec, ex, material)
    surface = PlatePhase(plate.pupil_phase(system.grid, dtype=dtype).to(device))
    values, arrays = _score(cfg, system, ms, {"ideal": mask, "exported": surface})
    sidecar = plate_sidecar(plate, ex, material, mask_cfg, spec)
    metrics = _metrics(values, sidecar, mask_cfg["kind"], dtype)
    lines = run_lines(material, system)
    if lines is not None:
        _line_outputs(run_dir, metrics, system, lines, mask, plate, material, mask_cfg["kind"], dtype)
    _write_plate(run_dir, plate, sidecar)
    io.save_figure(run_dir / "report.png", _report_figure(system, plate, sidecar, values, arrays, ex, material,
                                                          mask_cfg["kind"], ms.mtf_band))
    io.write_json(run_dir / "metrics.json", metrics)
    _log_result(values, metrics, sidecar, plate)
    log.info("wrote %s", run_dir)
    return values["exported"]["lsr"]


def _score(cfg: DictConfig, system, ms, designs: dict) -> tuple[dict, dict]:
    """Every figure of merit of each design (name -> mask), its limit and restorability: (values, arrays) by
    name."""
    limit = MTFLimit(system, ms.mtf_band)
    rest = restorability_tools(build_sensor_spec(cfg), build_scene_source(cfg.data), system, designs["ideal"],
                               None)
    values, arrays = {}, {}
    for name, design in designs.items():
        v, arr = evaluate_mask(system, design, ms.mtf_band, ms.lsr_p, ms.lsr_grids)
        v["lsr_limit"] = limit.lsr_limit(v["mtf_mean"], v["psf_energy_in_window"])
        v["lsr_over_limit"] = v["lsr"] / v["lsr_limit"]
        v["restorability"] = rest.score(design)
        values[name], arrays[name] = v, arr
    return values, arrays


def _metrics(values: dict, sidecar: dict, kind: str, dtype) -> dict:
    """metrics.json's entries: the ideal and exported figures, their changes and the plate's description."""
    ideal, exported = values["ideal"], values["exported"]
    return {
        **{f"{side}_{k}": values[side][k] for side in ("ideal", "exported") for k in FIGURES},
        "lsr_change": exported["lsr"] / ideal["lsr"] - 1,
        "mtf_mean_change": exported["mtf_mean"] / ideal["mtf_mean"] - 1,
        "restorability_change_db": exported["restorability"] - ideal["restorability"],
        **{k: sidecar[k] for k in ("pitch_m", "n", "size_m", "levels", "level_step_m", "material",
                                   "refractive_index", "wavelength_m", "full_wave_depth_m", "max_depth_m")},
        "mask_kind": kind, "precision": str(dtype).replace("torch.", ""),
    }


def _write_plate(run_dir: Path, plate, sidecar: dict) -> None:
    """The plate's heights [m] as .npy, 16-bit PNG and TIFF, and its description (export.json)."""
    height = plate.height.cpu().numpy()
    io.save_npy(run_dir / "height_m.npy", height)
    write_height_png(run_dir / "height.png", height, sidecar["metres_per_count"], sidecar)
    write_height_tiff(run_dir / "height.tif", height, sidecar["metres_per_count"], plate.pitch, sidecar)
    io.write_json(run_dir / "export.json", sidecar)


def _report_figure(system, plate, sidecar: dict, values: dict, arrays: dict, ex, material, kind: str, band):
    """report.png: the heights, the ideal and the exported PSF, their radial MTFs and the phase difference."""
    spec = system.spec
    f, rad_ideal, rad0 = arrays["ideal"]["mtf_radial"].cpu().numpy()
    rad_exp = arrays["exported"]["mtf_radial"][1].cpu().numpy()
    label = f"{ex.levels} levels" if ex.levels else "continuous"
    return export_figure(
        plate.height.cpu().numpy(), plate.inside.cpu().numpy(), plate.pitch,
        {f"ideal PSF, LSR {values['ideal']['lsr']:.4g}": arrays["ideal"]["psf"].cpu().numpy(),
         f"exported PSF ({label}), LSR {values['exported']['lsr']:.4g}": arrays["exported"]["psf"].cpu().numpy()},
        spec.focal_pitch_m, {"ideal": rad_ideal, f"exported ({label})": rad_exp, "uncoded": rad0}, f, band,
        phase_difference(arrays["exported"]["phase"], arrays["ideal"]["phase"], system.grid.aperture),
        spec.pupil_pitch_m,
        f"{kind} design in {material.name} at {spec.wavelength_m * 1e9:.4g} nm: max depth "
        f"{sidecar['max_depth_m'] * 1e6:.3f} um, pitch {plate.pitch * 1e6:.3g} um")


def _log_result(values: dict, metrics: dict, sidecar: dict, plate) -> None:
    """The ideal and the exported design's figures, one line each."""
    ideal, exported = values["ideal"], values["exported"]
    log.info("ideal: LSR %.4g, mtf_mean %.4g, %.2fx the limit, restorability %.2f dB", ideal["lsr"],
             ideal["mtf_mean"], ideal["lsr_over_limit"], ideal["restorability"])
    log.info("exported: LSR %.4g (%+.2f%%), mtf_mean %.4g (%+.2f%%), %.2fx the limit, restorability %.2f dB "
             "(%+.2f dB); max depth %.4g um (full wave %.4g um)", exported["lsr"], 100 * metrics["lsr_change"],
             exported["mtf_mean"], 100 * metrics["mtf_mean_change"], exported["lsr_over_limit"],
             exported["restorability"], metrics["restorability_change_db"], sidecar["max_depth_m"] * 1e6,
             plate.full_wave_depth_m * 1e6)
