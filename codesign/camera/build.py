"""A Camera from a composed configuration (the optics, mask, sensor and data blocks), every value validated first."""
from __future__ import annotations

import torch
from omegaconf import DictConfig, OmegaConf

from codesign.camera.camera import Camera
from codesign.data.scenes import data_config
from codesign.errors import ConfigError
from codesign.optics import OpticalSystem, OpticsSpec, build_mask
from codesign.sensor.simulator import SensorSimulator
from codesign.sensor.spec import SensorSpec


def sensor_spec(cfg: DictConfig) -> SensorSpec:
    """The SensorSpec of ``cfg.sensor`` at the network resolution of ``cfg.data`` (image_size, padded_size)."""
    sensor_cfg = OmegaConf.to_container(cfg.sensor, resolve=True)
    for key in ("image_size", "padded_size"):  # set by data.*, not a sensor.* key a user could type
        if key in sensor_cfg:
            raise ConfigError(f"sensor.{key}", sensor_cfg[key], f"unknown key: the network resolution is "
                              f"data.{key}")
    dc = data_config(cfg.data)  # data.image_size / padded_size validated under their own names first
    resolution = sensor_cfg.get("resolution", SensorSpec.resolution)
    if isinstance(resolution, int) and not isinstance(resolution, bool) and dc.image_size > resolution:
        raise ConfigError("data.image_size", dc.image_size, f"must be <= sensor.resolution ({resolution}): the "
                          "sensor is binned to the network resolution, never upsampled")
    sensor_cfg.update(image_size=dc.image_size, padded_size=dc.padded_size)
    return SensorSpec.from_config(sensor_cfg)


def build_camera(cfg: DictConfig, device, dtype=torch.float32) -> Camera:
    """Optical system, mask (frozen) and sensor simulator of a composed config, as one Camera."""
    optics = OpticsSpec.from_config(OmegaConf.to_container(cfg.optics, resolve=True))
    sensor = sensor_spec(cfg)
    system = OpticalSystem(optics, dtype=dtype, device=device)
    mask = build_mask(OmegaConf.to_container(cfg.mask, resolve=True), system.grid, optics.aperture_diameter_m)
    return Camera(system, mask, SensorSimulator(sensor, optics), device)
