"""Small geometries and helpers shared by the sensor tests.

Geometries (all at the Table 1 sensor pitch dx = 5.4 um, lambda f / W_a = 3.37 dx):
  * ``ODD``  = 48 pupil samples across the aperture, 33 x 33 focal window. A sensor with bin factor 1 or 3 then has
    a PSF kernel that spans exactly one window period (33 dx = 33 x dx = 11 x 3 dx).
  * ``EVEN`` = 48 pupil samples, 32 x 32 focal window (the brief's example). The odd kernel (33 fine / 9 coarse
    pixels at bin factor 4) spans more than the 32-sample window.
"""
from __future__ import annotations

import math
from functools import lru_cache

import torch

from codesign.data.params import fixed_scene_params
from codesign.optics import OpticalSystem, OpticsSpec
from codesign.optics.masks import published_halfring
from codesign.sensor.simulator import SensorSimulator, psf_state
from codesign.sensor.spec import SensorSpec

DX = 5.4e-6
ODD, EVEN = 33, 32

# "quiet": every noise term that can be switched off is off (quantization is always on).
QUIET = dict(alpha_l=0.0, alpha_b=0.0, laser_angle_rad=0.0, c1=0.0, c2=0.0, dark_current_mean_e=0.0,
             read_noise_mean_e=0.0, read_noise_std_e=0.0)
# every noise term on (the paper's figure values)
NOISY = dict(c1=0.2, c2=1.0, dark_current_mean_e=0.002, read_noise_mean_e=390.0, read_noise_std_e=10.5)


@lru_cache(maxsize=None)
def optics(focal_n: int = ODD) -> OpticsSpec:
    return OpticsSpec.with_samples_across(48, focal_n=focal_n)


@lru_cache(maxsize=None)
def system(focal_n: int = ODD, dtype: torch.dtype = torch.float64) -> OpticalSystem:
    return OpticalSystem(optics(focal_n), dtype=dtype)


@lru_cache(maxsize=None)
def states(focal_n: int = ODD, dtype: torch.dtype = torch.float64):
    """(coded state of the frozen published half ring, uncoded state with zero phase, uncoded window PSF h0)."""
    sysm = system(focal_n, dtype)
    with torch.no_grad():
        mask = published_halfring(sysm.grid, optics(focal_n).aperture_diameter_m)
        coded = psf_state(sysm, mask.phase())
        uncoded = psf_state(sysm, torch.zeros_like(sysm.grid.aperture))
        h0 = sysm.uncoded_psf()
    return coded, uncoded, h0


def make_sim(focal_n: int = ODD, resolution: int = 9, image_size: int = 9, padded_size: int | None = None,
             skip_unneeded: bool = True, **sensor_kw) -> SensorSimulator:
    """A small simulator. The out-of-window veil is off unless asked for: most tests check the window model
    (r_b = alpha_b (b * h) / sum(h0)) exactly; tests/sensor/test_veil.py covers the veil."""
    sensor_kw.setdefault("background_veil", False)
    spec = SensorSpec(resolution=resolution, image_size=image_size,
                      padded_size=image_size if padded_size is None else padded_size, **sensor_kw)
    return SensorSimulator(spec, optics(focal_n), skip_unneeded=skip_unneeded)


def params(batch: int = 1, dtype: torch.dtype = torch.float64, **values):
    """Scene parameters with every optional noise term off, overridden by ``values``."""
    return fixed_scene_params(batch, dtype=dtype, **{**QUIET, **values})


def uniform_scene(sim: SensorSimulator, value: float = 1.0, batch: int = 1, dtype=torch.float64) -> torch.Tensor:
    s = sim.scene_size
    return torch.full((batch, 1, s, s), float(value), dtype=dtype)


def random_scene(sim: SensorSimulator, batch: int = 1, seed: int = 0, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    s = sim.scene_size
    return torch.rand(batch, 1, s, s, generator=g, dtype=torch.float64).to(dtype)


def laser_angle(sim: SensorSimulator, row: float, col: float, level=None) -> tuple[float, float]:
    """Incidence angle (n_u, n_v) [rad] that centres the laser at (row, col) (pixel units) of a level's grid.

    Documented convention (SceneParams, PupilGrid): n_u is along u = x = columns, n_v along v = y = rows, so
    the focal offset is (x, y) = f (n_u, n_v) (checked by
    test_laser.test_incidence_angle_components_follow_the_optics_convention).
    """
    lvl = sim.coarse if level is None else level
    n = lvl.n_sensor
    f = sim.optics.focal_length_m
    return ((col - (n - 1) / 2) * lvl.pitch / f, (row - (n - 1) / 2) * lvl.pitch / f)


def full_well_dn(sim: SensorSimulator) -> float:
    return float(round(sim.sensor.gain_dn_per_e * sim.sensor.full_well_e))


def quant_std(sim: SensorSimulator) -> float:
    """Std of the direct path's Gaussian quantization noise, sqrt(w2 / 6), w2 = 1 / bin_factor^2."""
    return math.sqrt(1.0 / sim.sensor.bin_factor**2 / 6.0)
