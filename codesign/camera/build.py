"""A Camera from a composed configuration (the optics, mask, sensor and data blocks), every value validated first."""
from __future__ import annotations

import logging

import torch
from omegaconf import DictConfig, OmegaConf

from codesign.camera.camera import Camera
from codesign.config.runtime import to_container
from codesign.data.scenes import DataConfig
from codesign.errors import ConfigError, require_number
from codesign.optics import OpticalSystem, OpticsSpec, build_mask
from codesign.optics.lines import LaserLines
from codesign.optics.materials import Material
from codesign.optics.measured import load_measured
from codesign.sensor.simulator import SensorSimulator
from codesign.sensor.spec import SensorSpec

log = logging.getLogger("codesign.camera")


def build_sensor_spec(cfg: DictConfig) -> SensorSpec:
    """The SensorSpec of ``cfg.sensor`` at the network resolution of ``cfg.data`` (image_size, padded_size)."""
    sensor_cfg = OmegaConf.to_container(cfg.sensor, resolve=True)
    for key in ("image_size", "padded_size"):  # set by data.*, not a sensor.* key a user could type
        if key in sensor_cfg:
            raise ConfigError(f"sensor.{key}", sensor_cfg[key], f"unknown key: the network resolution is "
                              f"data.{key}")
    dc = DataConfig.from_config(cfg.data)  # data.image_size / padded_size validated under their own names first
    # sensor.resolution's own bounds first (SensorSpec's): sensor.resolution=0 was reported as a data.image_size
    # error, naming a key nobody typed and never the bound of the one typed
    resolution = require_number("sensor.resolution", sensor_cfg.get("resolution", SensorSpec.resolution), lo=8,
                                hi=65536, integer=True)
    if dc.image_size > resolution:
        raise ConfigError("data.image_size", dc.image_size, f"must be <= sensor.resolution ({resolution}): the "
                          "sensor is binned to the network resolution, never upsampled")
    sensor_cfg.update(image_size=dc.image_size, padded_size=dc.padded_size)
    return SensorSpec.from_config(sensor_cfg)


def build_camera(cfg: DictConfig, device, dtype=torch.float32) -> Camera:
    """Optical system, mask (frozen) and sensor simulator of a composed config, as one Camera; with the measured
    PSF of ``optics.psf_file`` in place of the computed one when it is set (its files checked first)."""
    optics = OpticsSpec.from_config(OmegaConf.to_container(cfg.optics, resolve=True))
    measured = load_measured(optics)
    sensor = build_sensor_spec(cfg)
    system = OpticalSystem(optics, dtype=dtype, device=device)
    mask = build_mask(OmegaConf.to_container(cfg.mask, resolve=True), system.grid, optics.aperture_diameter_m)
    if measured is not None:
        log.info("optics.psf_file: the measured PSF %s (%d x %d px of %.3g m%s) replaces the %s mask's computed PSF%s",
                 measured.path, measured.shape[1], measured.shape[0], measured.pitch_m,
                 f", dark frame {measured.dark_path} subtracted" if measured.dark_path else "", mask.kind,
                 "; sensor.laser_halo is off for it: the light beyond a measured frame is not known"
                 if sensor.laser_halo else "")
    lam = sensor.wavelength_laser_m
    if measured is not None and not optics.is_design_wavelength(lam):
        raise ConfigError("sensor.wavelength_laser_m", lam, f"a measured PSF (optics.psf_file) holds one "
                          f"wavelength, the design's ({optics.wavelength_m:g} m): a laser at another line needs the "
                          f"mask's computed PSF there; set sensor.wavelength_laser_m={optics.wavelength_m:g} or "
                          f"optics.psf_file=null")
    if measured is not None and optics.scene_spectrum is not None:
        raise ConfigError("optics.scene_spectrum", [list(p) for p in optics.scene_spectrum], "a measured PSF "
                          "(optics.psf_file) is the scene's PSF as measured: set optics.scene_spectrum=null, or "
                          "optics.psf_file=null to compute the band's PSF from the mask")
    # the material is read where a wavelength other than the design's needs it (fused silica when a config has none)
    other = optics.scene_spectrum is not None or not optics.is_design_wavelength(sensor.wavelength_laser_m)
    material = Material.from_config(to_container(cfg.get("material"))) if other else None
    return Camera(system, mask, SensorSimulator(sensor, optics), device, measured,
                  laser_line(material, system, sensor), scene_spectrum(material, system))


def scene_spectrum(material: Material | None, system: OpticalSystem) -> tuple | None:
    """(LaserLines of optics.scene_spectrum's wavelengths through ``material``, their weights), or None for the
    design wavelength."""
    spectrum = system.spec.scene_spectrum
    if spectrum is None:
        return None
    for lam, _ in spectrum:
        material.check_wavelength(lam)
    lines = LaserLines(system, material.index, tuple(lam for lam, _ in spectrum))
    log.info("the scene over %d wavelengths (%s nm, weights %s): its PSF is their weighted mean", len(spectrum),
             ", ".join(f"{lam * 1e9:.1f}" for lam, _ in spectrum), ", ".join(f"{w:g}" for _, w in spectrum))
    return lines, tuple(w for _, w in spectrum)


def laser_line(material: Material | None, system: OpticalSystem, sensor: SensorSpec) -> LaserLines | None:
    """The LaserLines of the laser's line (sensor.wavelength_laser_m) when it is not the design wavelength: the
    mask's surface (optics.wrap_waves, ``material``) seen there; None at the design wavelength."""
    lam, spec = sensor.wavelength_laser_m, system.spec
    if spec.is_design_wavelength(lam):
        return None
    material.check_wavelength(lam)
    line = LaserLines(system, material.index, (lam,))
    log.info("the laser at %.1f nm, the scene at %.1f nm: the laser sees the %s's phase scaled by %.4f (%s)",
             lam * 1e9, spec.wavelength_m * 1e9, "surface" if spec.wrap_waves is None else
             f"{spec.wrap_waves}-wave wrapped plate", line.scales[0], material.name)
    return line
