"""What a mask search sets up from its settings: the constraint levels, the start vector, the restorability that
scores every design, and the figures of a design after quantization."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from codesign.camera import Camera
from codesign.data.source import SceneSource
from codesign.design.problem import Limits, psf_state_of
from codesign.design.restorability import Restorability, restorability_for
from codesign.errors import ConfigError
from codesign.sensor.simulator import SensorSimulator
from codesign.sensor.spec import SensorSpec


@dataclass
class RestorabilityTools:
    """The Restorability of a search's optics and sensor, and the camera whose kernels it scores."""

    module: Restorability
    camera: Camera

    @property
    def pair(self) -> tuple:
        """(restorability module, camera): what a DesignProblem takes to score restorability."""
        return self.module, self.camera

    @torch.no_grad()
    def score(self, mask) -> float:
        """Expected Wiener PSNR [dB] of ``mask`` on the search's optics."""
        system = self.camera.system
        kernel = self.camera.simulator.kernel(psf_state_of(system, system.mask_psf(mask)))
        return float(self.module(kernel))


def restorability_tools(sensor: SensorSpec, source: SceneSource, system, mask, alpha_l: float | None
                        ) -> RestorabilityTools:
    """Restorability at the sensor and network size of ``sensor`` (its image_size: data.image_size), with the scene
    spectrum fitted to the training split of ``source`` (data.*'s scenes)."""
    lam = system.spec.wavelength_m
    if alpha_l is not None and not system.spec.is_design_wavelength(sensor.wavelength_laser_m):
        raise ConfigError("search.restorability_alpha_l", alpha_l, f"counts the laser's saturated footprint at the "
                          f"design wavelength ({lam:g} m), not at sensor.wavelength_laser_m = "
                          f"{sensor.wavelength_laser_m:g}: set search.restorability_alpha_l=null, or the laser back "
                          f"to the design wavelength")
    camera = Camera(system, mask, SensorSimulator(sensor, system.spec), system.grid.rho.device)
    scenes = source.fixed_batch(source.split_names("train"), sensor.image_size)
    return RestorabilityTools(restorability_for(camera, scenes, alpha_l=alpha_l), camera)


def search_limits(s, mask, base: dict, base_arr: dict, limit, lsr_p: float) -> Limits:
    """The constraint levels of SearchSpec ``s`` for ``mask``; ``base``/``base_arr``: the published mask's
    figures; ``limit``: the MTFLimit (a floor it puts out of any phase mask's reach is refused)."""
    mtf = None
    if s.mtf_floor is not None:
        mtf = (base["mtf_mean"] if s.mtf_floor == "published" else s.mtf_floor) * s.mtf_floor_factor
        main = ("search.mtf_floor_factor", s.mtf_floor_factor) if s.mtf_floor == "published" else \
            ("search.mtf_floor", s.mtf_floor)
        for (k, value), factor in [(main, s.mtf_floor_factor)] + [((f"search.pareto_factors[{i}]", f), f)
                                                                   for i, f in enumerate(s.pareto_factors or ())]:
            level = mtf / s.mtf_floor_factor * factor
            if not level < limit.uncoded_mtf_mean:
                raise ConfigError(k, value, f"gives the MTF floor {level:.4g}, at or above the uncoded aperture's "
                                  f"mtf_mean {limit.uncoded_mtf_mean:.4g}, which no phase mask can reach: the floor "
                                  f"must be below {limit.uncoded_mtf_mean:.4g} (the published mask's mtf_mean is "
                                  f"{base['mtf_mean']:.4g})")
    energy = mask.design_energy_floor if s.energy_floor == "auto" else s.energy_floor
    if energy == "published":
        energy = float(base_arr["psf"].sum())
    # the smooth LSR bounds the sampled peak from above: a design under the published mask's sampled peak is below it
    ceiling = base["lsr_sampled"] if s.lsr_ceiling == "published" else s.lsr_ceiling
    step = mask.resolution_step if s.max_phase_step == "auto" else s.max_phase_step
    return Limits(mtf=mtf, energy=energy, restorability=s.restorability_floor, lsr=ceiling, step=step)


def start_init(init: str, mask) -> str:
    """``search.init`` with auto resolved to the family's start."""
    return mask.search_start if init == "auto" else init


def start_vector(init: str, mask, published, defocus_rad: float) -> torch.Tensor | None:
    """The parameter vector of start 0 (``init`` resolved by start_init): the configured mask (mask), the published
    mask in this family (published), a defocus of ``defocus_rad`` (defocus) or None (random)."""
    if init == "mask":
        return mask.to_vector()
    if init == "random":
        return None
    if init == "defocus":
        if not mask.fits_phases:
            raise ConfigError("search.init", init, f"a {mask.kind} mask cannot take a defocus phase: use "
                              "search.init=published, mask or random")
        return mask.defocus_vector(defocus_rad)
    if mask.kind == "halfring":
        if published.vector_size != mask.vector_size:
            raise ConfigError("search.init", init, f"the configured mask has {mask.vector_size // 2} rings, the "
                              f"published one {published.vector_size // 2}: use search.init=mask or random")
        return published.to_vector()
    if mask.fits_phases:
        return mask.phase_vector(published.phase().detach())
    raise ConfigError("search.init", init, f"a {mask.kind} mask has no published form: use search.init=mask or "
                      "random")


@torch.no_grad()
def quantized_figures(mask, monitor, rest, levels=(2, 4, 8, 16)) -> dict:
    """LSR (continuous peak), mtf_mean, window energy and restorability of ``mask`` with its phase quantized to each
    number of levels (the mask is left as it was)."""
    keep, out = mask.levels, {}
    try:
        for k in levels:
            mask.levels = k
            v, arr = monitor.measure(mask, refine=True)
            out[str(k)] = {"lsr": v["lsr"], "mtf_mean": v["mtf_mean"], "window_energy": float(arr["psf"].sum()),
                           "restorability": rest.score(mask)}
    finally:
        mask.levels = keep
    return out
