"""What export and tolerance share: the design's plate and what a shop needs besides its heights (their settings
are validated before any work by codesign.experiments.specs.plate_settings)."""
from __future__ import annotations

import torch

from codesign.fab.surface import ExportSpec, Plate, fab_grid
from codesign.fab.writers import FULL_SCALE
from codesign.optics import OpticsSpec, build_mask
from codesign.optics.materials import Material


def build_plate(mask_settings: dict, spec: OpticsSpec, ex: ExportSpec, material: Material) -> Plate:
    """The plate of the design ``mask_settings`` (a mask block, as build_mask takes): its phase evaluated on the
    fabrication grid, wrapped, quantized, as heights."""
    n = ex.plate_n(spec)
    grid = fab_grid(spec, ex.pitch_m, n)
    with torch.no_grad():
        phase = build_mask(mask_settings, grid, spec.aperture_diameter_m).freeze().phase()
    return Plate.from_phase(phase, grid, spec.wavelength_m, material.index(spec.wavelength_m), ex.levels,
                            spec.wrap_waves)


def plate_sidecar(plate: Plate, ex: ExportSpec, material: Material, mask_settings: dict, spec: OpticsSpec) -> dict:
    """What a shop needs besides the heights: grid, levels, material, wavelength, depths, the image scale; the
    design named by its mask settings' kind, init and preset."""
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
        "design": {k: mask_settings.get(k) for k in ("kind", "init", "preset") if mask_settings.get(k) is not None},
        "export": {"pitch_m": ex.pitch_m, "size_m": ex.size_m, "levels": ex.levels},
    }
