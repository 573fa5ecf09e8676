"""``data.masks``: one restorer for many masks, trained over a pool of them.

A restorer takes the system's OTF beside the sensor image, so one network can restore through any mask it is given,
if it has seen many while it learned. With ``data.masks`` set, a restorer's training batches are imaged through a
fixed pool of frozen masks, another one drawn every ``data.mask_every`` steps, and each batch carries its mask's OTF;
validation and evaluation keep the configured mask (``mask``). Pool members, each a string:

- ``published``: the published five half rings (under the configured conventions when ``mask`` is a half ring);
- ``defocus:R``: a spline surface holding a defocus of R rad at the pupil's edge (R = 20 to 60 gives near flat-top
  PSFs whose LSR spans about 1e-3 to 1e-4 at the default optics);
- a mask record (``best_mask.json`` of a search, ``learned_mask.json`` of a joint run), any family.

``data.mask_draws`` adds that many random draws around every member: its parameter vector plus ``data.mask_jitter``
times its RMS value times a standard normal draw per parameter, kept in the family's bounds. The pool is fixed at the
start (every member's optics computed once and cached; a mask's laser halo takes seconds), and which member serves
step k is a function of (seed, k // mask_every) alone, so a resumed run trains on the masks an uninterrupted one does.
"""
from __future__ import annotations

import copy
import logging
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from codesign.camera import Camera
from codesign.config.runtime import to_container
from codesign.data.scenes import DataConfig
from codesign.errors import ConfigError
from codesign.optics.masks import FAMILIES, build_mask, load_record, published_mask_config
from codesign.optics.lines import LaserLines
from codesign.optics.materials import Material
from codesign.sensor.simulator import SensorSimulator
from codesign.sensor.spec import SensorSpec, kernel_size
from codesign.train.mask_draws import random_family_masks

log = logging.getLogger("codesign.train")

def pool_settings(dc: DataConfig) -> dict | None:
    """The checked data.masks / mask_every / mask_draws / mask_jitter of ``dc``, or None when data.masks is null;
    every member's family ("masks": (member, family) pairs, None for 'published' and 'defocus:R')."""
    if dc.masks is None:
        return None
    members = [(str(m), _check_item(f"data.masks[{i}]", m)) for i, m in enumerate(dc.masks)]
    return {"masks": members, "every": dc.mask_every, "draws": dc.mask_draws, "jitter": dc.mask_jitter,
            "lsr": dc.mask_lsr, "scales": dc.scales}


def _check_item(key: str, item) -> str | None:
    """The family of a record member (its record read and checked whole), None for a named one."""
    if not isinstance(item, str) or not item.strip():
        raise ConfigError(key, item, "must be 'published', 'defocus:R' or the path of a mask record")
    if item == "published":
        return None
    if item.startswith("random:"):
        random_member(key, item)
        return None
    if item.startswith("defocus:"):
        try:
            value = float(item.split(":", 1)[1])
        except ValueError:
            value = float("nan")
        if not 0 < value <= 200:
            raise ConfigError(key, item, "a defocus member is 'defocus:R' with R a number of rad in (0, 200]")
        return None
    if not Path(item).expanduser().is_file():
        raise ConfigError(key, item, "is neither 'published', 'defocus:R' nor an existing mask record file")
    return load_record(item, key, "must be 'published', 'defocus:R' or the path of a mask record")["kind"]


def random_member(key: str, item: str) -> tuple[str, int]:
    """(family, count) of a 'random:FAMILY[:N]' member, checked."""
    parts = item.split(":")
    allowed = f"a random member is 'random:FAMILY' or 'random:FAMILY:N', FAMILY one of {', '.join(sorted(FAMILIES))}"
    if len(parts) not in (2, 3) or parts[1] not in FAMILIES:
        raise ConfigError(key, item, allowed)
    try:
        count = int(parts[2]) if len(parts) == 3 else 1
    except ValueError:
        count = 0
    if not 1 <= count <= 1000:
        raise ConfigError(key, item, allowed + " and N an integer in [1, 1000]")
    return parts[1], count


def _member_masks(item: str, kind: str | None, published: dict, system, draws: int, jitter: float, rng,
                  lsr_range: tuple[float, float]) -> list:
    """(name, frozen Mask) of the member ``item`` (``kind``: its record's family) and its ``draws`` random draws
    around it; a 'random:FAMILY:N' member is N random masks of the family (codesign/train/mask_draws.py).
    ``published``: the mask settings of the published mask under the run's conventions (published_mask_config)."""
    grid, aperture_m = system.grid, system.spec.aperture_diameter_m
    if item.startswith("random:"):
        family, count = random_member("data.masks", item)
        return random_family_masks(family, count, system, aperture_m, rng, lsr_range)
    if item == "published":
        mask = build_mask(published, grid, aperture_m, prefix="data.masks")
    elif item.startswith("defocus:"):
        mask = build_mask({**FAMILIES["spline"].Spec.defaults(), "kind": "spline"}, grid, aperture_m,
                          prefix="data.masks")
        mask.set_vector(mask.defocus_vector(float(item.split(":", 1)[1])))
    else:
        mask = build_mask({**FAMILIES[kind].Spec.defaults(), "kind": kind, "init": str(Path(item).expanduser())},
                          grid, aperture_m, prefix="data.masks")
    out = [(item, mask.freeze())]
    x = mask.to_vector()
    lo, hi = mask.bounds()
    scale = float(x.square().mean().sqrt())
    for k in range(draws):
        drawn = copy.deepcopy(mask)
        step = torch.from_numpy(rng.standard_normal(x.numel())) * (jitter * scale)
        drawn.set_vector(torch.minimum(torch.maximum(x + step, lo), hi))
        drawn.project()
        out.append((f"{item} draw {k + 1}", drawn.freeze()))
    return out


class MaskPool:
    """Frozen cameras, one per pool member, sharing the optical system (and the laser line and the scene's band) of
    ``base``; each has its own sensor simulator, so that every member keeps its kernels cached."""

    def __init__(self, names: list[str], cameras: list[Camera], every: int, seed: int):
        self.names, self.cameras, self.every, self.seed = names, cameras, every, seed
        self._active: Camera | None = None  # the member imaging now: the only one whose kernels are kept

    def index(self, step: int) -> int:
        """The member serving training step ``step``: drawn from (seed, step // every) alone (resumes exactly)."""
        gen = torch.Generator().manual_seed(self.seed * 1_000_003 + step // self.every + 17)
        return int(torch.randint(len(self.cameras), (1,), generator=gen))

    def camera(self, step: int) -> Camera:
        """The member of step ``step``; the one before it, when another, releases its kernels and PSF spectra
        (tens of MB each: a pool of 150 cameras would otherwise keep gigabytes; recomputed, identical, when it
        serves again). Optics, OTF and laser halo stay."""
        cam = self.cameras[self.index(step)]
        if self._active is not None and self._active is not cam:
            self._active.release_simulation_cache()
        self._active = cam
        return cam

    def lsr(self) -> list[float]:
        """Each member's sampled LSR (window PSF peak / unmasked peak; the certified peak is a search's job)."""
        out = []
        for cam in self.cameras:
            state = cam.frozen_optics().state
            out.append(float(state.psf.max() / state.uncoded_peak))
        return out

    def report(self) -> list[dict]:
        """One row per member, {"mask": its name, "lsr_sampled": its sampled LSR}: the pool's record in metrics.json."""
        return [{"mask": n, "lsr_sampled": v} for n, v in zip(self.names, self.lsr())]


def scaled_sensor(sensor: SensorSpec, optics, scale: int, key: str = "data.scales") -> SensorSpec:
    """The run's sensor seen at pixel scale ``scale``: the whole sensor binned to ``scale`` px per side, of which the
    network sees ``sensor.image_size`` px (a crop of the same pitch: a smaller sensor of sensor.image_size * bin
    pixels), padded so that the PSF kernel at that pitch does not wrap in a deconvolution."""
    if scale > sensor.resolution:
        raise ConfigError(key, scale, f"must be <= sensor.resolution ({sensor.resolution}): the sensor is binned, "
                          "never upsampled")
    n = sensor.image_size
    resolution = max(n, round(n * sensor.resolution / scale))
    k = kernel_size(optics.focal_extent_m, sensor.pixel_pitch_m * resolution / n)
    padded = max(sensor.padded_size, -(-(n + k - 1) // 8) * 8)
    return sensor.replace(resolution=resolution, padded_size=padded)


def laser_lines(material: Material | None, base: Camera) -> list[tuple]:
    """(name, sensor spec, LaserLines or None) of every laser line the pool's lasers shine at: each of
    optics.laser_wavelengths_m when it is set (the lines the mask must protect against: the restorer meets their
    PSFs too), seen through ``material`` (material.*; needed then only), else the run's own
    (sensor.wavelength_laser_m); name None for the run's own alone."""
    system, sensor = base.system, base.simulator.sensor
    wavelengths = system.spec.laser_wavelengths_m
    if not wavelengths:
        return [(None, sensor, base.laser_line)]
    out = []
    for lam in wavelengths:
        line = None if system.spec.is_design_wavelength(lam) else LaserLines(system, material.index, (lam,))
        out.append((f"laser {lam * 1e9:.0f} nm", sensor.replace(wavelength_laser_m=lam), line))
    return out


def build_mask_pool(cfg: DictConfig, base: Camera, seed: int) -> MaskPool | None:
    """The pool of ``data.masks`` (times ``data.scales``, times the laser lines of optics.laser_wavelengths_m) around
    ``base`` (the run's camera), or None when data.masks is null; every member built and its optics computed before
    training starts."""
    dc = DataConfig.from_config(cfg.data)  # the list and the numbers, checked under their keys
    settings = pool_settings(dc)
    if settings is None:
        scales = dc.scales
        if scales is not None:
            raise ConfigError("data.scales", list(scales), "trains over pixel scales with a pool of masks: set "
                              "data.masks too (e.g. [published]), or leave data.scales null")
        return None
    if base.measured is not None:
        raise ConfigError("data.masks", [m for m, _ in settings["masks"]], "trains over computed masks: a measured PSF "
                          "(optics.psf_file) fixes the optics (leave one of them null)")
    system, sensor = base.system, base.simulator.sensor
    scales = settings["scales"] or (None,)
    lines_at = system.spec.laser_wavelengths_m  # the material only where the lines need it
    lines = laser_lines(Material.from_config(to_container(cfg.get("material"))) if lines_at else None, base)
    published = published_mask_config(to_container(cfg.mask))
    rng = np.random.default_rng(seed + 424243)
    names, cameras = [], []
    for item, kind in settings["masks"]:
        for name, mask in _member_masks(item, kind, published, system, settings["draws"], settings["jitter"], rng,
                                        settings["lsr"]):
            for line_name, laser_sensor, line in lines:
                donor = None
                for scale in scales:
                    spec = laser_sensor if scale is None else scaled_sensor(laser_sensor, system.spec, scale)
                    sim = SensorSimulator(spec, base.simulator.optics, base.simulator.skip_unneeded)
                    cam = Camera(system, mask, sim, base.device, None, line, base.scene_spectrum)
                    cam.halo_donor = donor  # the coarsest scale's sensor is the largest: its far PSF covers the rest
                    donor = donor or cam
                    cameras.append(cam)
                    names.append(" @ ".join(n for n in (name, None if scale is None else f"{scale} px", line_name)
                                            if n))
    pool = MaskPool(names, cameras, settings["every"], seed)
    lsr = pool.lsr()
    for cam in cameras:  # computing the optics kept every member's spectra: only the imaging one keeps them
        cam.release_simulation_cache()
    log.info("data.masks: %d cameras (%d listed masks, %d draws each at jitter %g; %s; %d laser line(s)), a new "
             "one every %d steps; sampled LSR %.3g to %.3g", len(cameras), len(settings["masks"]), settings["draws"],
             settings["jitter"], "pixel scales " + ", ".join(map(str, scales)) if scales[0] is not None else
             "the run's pixel scale", len(lines), settings["every"], min(lsr), max(lsr))
    return pool
