"""What export and tolerance share: their settings validated before any work, and the design's plate."""
from __future__ import annotations

import logging

import torch
from omegaconf import DictConfig

from codesign.config.runtime import resolve_dtype, to_container
from codesign.errors import ConfigError
from codesign.optics.metrics import require_band_frequencies
from codesign.design.merit import metrics_spec
from codesign.optics.materials import Material, material_of
from codesign.fab.surface import ExportSpec, Plate, fab_grid
from codesign.fab.writers import FULL_SCALE
from codesign.optics import OpticsSpec, build_mask
from codesign.optics.masks import config_of_design, levels_of_design


def setup(cfg: DictConfig) -> tuple:
    """Every setting validated before any work: (optics, export, material, mask config, dtype)."""
    spec = OpticsSpec.from_config(to_container(cfg.optics))
    ex = ExportSpec.from_config(to_container(cfg.get("export")))
    material = material_of(cfg)
    material.index(spec.wavelength_m)
    ex.plate_n(spec)
    if ex.levels is not None and spec.wrap_waves is None:
        raise ConfigError("export.levels", ex.levels, "a continuous surface (optics.wrap_waves = null) has no etch "
                          "levels: set export.levels=null, or wrap the surface (optics.wrap_waves=1, or m for an "
                          "m-wave multi-order plate)")
    require_band_frequencies(spec, metrics_spec(cfg).mtf_band)  # both report mtf_means of the window
    mask_cfg = config_of_design(to_container(cfg.mask))
    design = levels_of_design(mask_cfg)
    # an 8-level design is built as 8 levels (a continuous surface has none: its phase steps are kept as they are)
    if ex.levels is None and design is not None and design <= 256 and spec.wrap_waves is not None:
        logging.getLogger("codesign.export").info("export.levels = null: the design has %d levels, so has the "
                                                  "plate (export.levels chooses others)", design)
        ex = ex.replace(levels=design)
    dtype = resolve_dtype("precision", cfg.get("precision"))
    return spec, ex, material, mask_cfg, dtype


def make_plate(mask_cfg: dict, spec: OpticsSpec, ex: ExportSpec, material: Material) -> Plate:
    """The design's plate: its phase evaluated on the fabrication grid, wrapped, quantized, as heights."""
    n = ex.plate_n(spec)
    grid = fab_grid(spec, ex.pitch_m, n)
    with torch.no_grad():
        phase = build_mask(mask_cfg, grid, spec.aperture_diameter_m).freeze().phase()
    return Plate.from_phase(phase, grid, spec.wavelength_m, material.index(spec.wavelength_m), ex.levels,
                            spec.wrap_waves)


def plate_sidecar(plate: Plate, ex: ExportSpec, material: Material, mask_cfg: dict, spec: OpticsSpec) -> dict:
    """What a shop needs besides the heights: grid, levels, material, wavelength, depths, the image scale."""
    inside = plate.height[plate.inside]
    return {
        "units": "metres", "pitch_m": plate.pitch, "n": plate.n, "size_m": plate.n * plate.pitch,
        "origin": "pixel (n // 2, n // 2) on the optical axis; row = v, column = u; heights above the unetched "
                  "surface (0 = not etched; outside the aperture's support 0)",
        "levels": plate.n_levels, "level_step_m": plate.step_m, "wrap_waves": plate.wrap_waves,
        "depth_range_m": plate.depth_m,
        **material.summary(spec.wavelength_m), "wavelength_m": spec.wavelength_m,
        "full_wave_depth_m": plate.full_wave_depth_m, "max_depth_m": float(inside.max()) if inside.numel() else 0.0,
        "aperture_diameter_m": spec.aperture_diameter_m,
        "metres_per_count": plate.depth_m / FULL_SCALE,
        "design": {k: mask_cfg.get(k) for k in ("kind", "init", "preset") if mask_cfg.get(k) is not None},
        "export": {"pitch_m": ex.pitch_m, "size_m": ex.size_m, "levels": ex.levels},
    }
