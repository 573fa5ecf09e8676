"""Monte Carlo over fabrication and assembly errors of a plate: which errors cost the design its laser protection.

Error sources (each a zero-mean Gaussian with the configured 1-sigma):
- depth_scale: every height scaled by (1 + e) (etch rate or resist contrast off by e);
- level_noise: each etch level's height off by its own error (a quantized plate); on a continuous plate an
  independent height error at every pupil sample (roughness at the design's sampling);
- shift: the plate displaced laterally in the pupil by (dx, dy), each axis with the sigma;
- rotation: the plate rotated about the axis;
- wavelength: the laser at lambda + d: the same heights give 2 pi (n(lambda + d) - 1) h / (lambda + d), and the PSF
  scales with lambda (the system is rebuilt at that wavelength, its uncoded peak with it);
- defocus: the sensor displaced along the axis by dz: the phase pi dz rho^2 / (lambda f^2) (paraxial).
The aperture stop stays where it is; the plate is patterned over the aperture's support (for the default
super-Gaussian order 4 % beyond the clear radius, 75 um at W_a = 3.83 mm): a shift beyond that brings unpatterned
(flat) plate into the beam, as in the lab. The LSR of every sample is its sampled peak over the uncoded peak at the
sample's wavelength. A sample with every error 0 is the plate as exported (exactly the export's figures).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import torch

from codesign.config.store import register, spec_node
from codesign.optics.metrics import require_band_frequencies
from codesign.errors import ConfigError, require_number, round_down
from codesign.optics.materials import Material
from codesign.fab.surface import Plate, phase_of_height
from codesign.optics import OpticalSystem, RadialMTF, metrics
from codesign.spec_base import SpecMixin

# a detuned wavelength's samples reach this many sigma (10^6 samples pass 6 sigma with probability 2e-3)
DETUNING_SIGMAS = 6
SOURCES = ("depth_scale", "level_noise", "shift", "rotation", "wavelength", "defocus")
_SIGMA_KEYS = {"depth_scale": "depth_scale", "level_noise": "level_noise_m", "shift": "shift_m",
               "rotation": "rotation_deg", "wavelength": "wavelength_m", "defocus": "defocus_m"}


@dataclass(frozen=True)
class ToleranceSpec(SpecMixin):
    """samples: Monte Carlo samples with every source at once (the yield); samples_per_source: samples of each
    source alone (its LSR distribution); the 1-sigma of each source (0 = off): depth_scale (relative),
    level_noise_m [m], shift_m [m per axis], rotation_deg [deg], wavelength_m [m], defocus_m [m of sensor
    travel]; lsr_ceiling: the yield counts samples with LSR <= this (auto: 1.2 x the exported design's LSR, i.e.
    losing at most a sixth of its protection; or a number); batch: samples propagated together; seed."""

    samples: int = 1000
    samples_per_source: int = 200
    depth_scale: float = 0.03
    level_noise_m: float = 10e-9
    shift_m: float = 10e-6
    rotation_deg: float = 0.5
    wavelength_m: float = 2e-9
    defocus_m: float = 50e-6
    lsr_ceiling: float | str = "auto"
    batch: int = 16
    seed: int = 0
    prefix: str = field(default="tolerance", compare=False, repr=False)

    def __post_init__(self) -> None:
        p = self.prefix
        # samples_per_source >= 1: 0 ran the analysis, wrote samples.csv, then failed on a zero-size array
        for k, hi in (("samples", 10**6), ("samples_per_source", 10**6), ("batch", 1024)):
            object.__setattr__(self, k, require_number(f"{p}.{k}", getattr(self, k), lo=1, hi=hi, integer=True))
        for source, key in _SIGMA_KEYS.items():
            hi = {"depth_scale": 0.5, "rotation_deg": 45.0}.get(key, 1e-3)
            require_number(f"{p}.{key}", getattr(self, key), lo=0, hi=hi)
        if self.lsr_ceiling != "auto":
            if isinstance(self.lsr_ceiling, str):
                raise ConfigError(f"{p}.lsr_ceiling", self.lsr_ceiling, "must be auto or a number > 0")
            require_number(f"{p}.lsr_ceiling", self.lsr_ceiling, lo=0, lo_open=True)
        object.__setattr__(self, "seed", require_number(f"{p}.seed", self.seed, lo=0, hi=2**63 - 1, integer=True))

    def check_detuning(self, optics) -> None:
        """tolerance.wavelength_m against the design's OpticsSpec, before any work: its samples reach the design
        wavelength +- DETUNING_SIGMAS sigma, each one the window must carry (a wider sigma failed mid-run, named as a
        sample's optics.wavelength_m = -5.5e-07)."""
        sigma, lam = self.wavelength_m, optics.wavelength_m
        shortest = max(1e-8, optics.focal_extent_m * optics.pupil_pitch_m / optics.focal_length_m,  # aliasing
                       2 * optics.focal_pitch_m * optics.aperture_diameter_m / optics.focal_length_m)  # sampling
        most = min((lam - shortest) / DETUNING_SIGMAS, (1e-4 - lam) / DETUNING_SIGMAS)
        if sigma <= max(most, 0.0):
            return
        allowed = f"<= {round_down(most):.3g} m" if most > 0 else "0 (the design wavelength is the window's limit)"
        raise ConfigError(f"{self.prefix}.wavelength_m", sigma, f"its samples reach optics.wavelength_m +- "
                          f"{DETUNING_SIGMAS} sigma = {lam:.4g} +- {DETUNING_SIGMAS * sigma:.3g} m, beyond the "
                          f"{shortest:.3g}..1e-04 m the optics window carries (a shorter wavelength aliases or is "
                          f"undersampled on it): must be >= 0 and {allowed}")

    def sigma(self, source: str) -> float:
        """The 1-sigma error of ``source`` (one of SOURCES), in that source's unit."""
        return float(getattr(self, _SIGMA_KEYS[source]))

    def ceiling(self, nominal_lsr: float) -> float:
        """The yield's LSR ceiling: 1.2 x ``nominal_lsr`` with lsr_ceiling auto, else the given value."""
        return 1.2 * nominal_lsr if self.lsr_ceiling == "auto" else float(self.lsr_ceiling)


@dataclass
class Errors:
    """B samples of every error source (zeros where a source is off): depth (B,), level (B, K) [m] or None,
    roughness (B,) 1-sigma of a continuous plate's per-sample noise [m], dx, dy [m], rotation [rad],
    wavelength (B,) offsets [m], dz [m]."""

    depth: torch.Tensor
    level: torch.Tensor | None
    roughness: torch.Tensor
    dx: torch.Tensor
    dy: torch.Tensor
    rotation: torch.Tensor
    wavelength: torch.Tensor
    dz: torch.Tensor

    @classmethod
    def zeros(cls, b: int, n_levels: int | None) -> "Errors":
        """``b`` samples with every error zero (the nominal plate; ``n_levels``: its etch levels, or None)."""
        z = torch.zeros(b, dtype=torch.float64)
        level = None if n_levels is None else torch.zeros(b, n_levels, dtype=torch.float64)
        return cls(z, level, z.clone(), z.clone(), z.clone(), z.clone(), z.clone(), z.clone())

    def __len__(self) -> int:
        return self.depth.numel()

    def take(self, idx) -> "Errors":
        """The samples at ``idx`` (an index or a slice along B)."""
        return Errors(*(None if v is None else v[idx] for v in self.__dict__.values()))

    def columns(self) -> dict[str, torch.Tensor]:
        """The per-sample scalars of a samples table (a level error as its RMS over the levels)."""
        level = torch.zeros_like(self.depth) if self.level is None else self.level.pow(2).mean(-1).sqrt()
        return {"depth_scale": self.depth, "level_rms_m": level, "roughness_m": self.roughness, "dx_m": self.dx,
                "dy_m": self.dy, "rotation_deg": torch.rad2deg(self.rotation), "dlambda_m": self.wavelength,
                "dz_m": self.dz}


def draw(spec: ToleranceSpec, sources: tuple[str, ...], b: int, n_levels: int | None,
         gen: torch.Generator) -> Errors:
    """``b`` samples of the given sources (the others 0)."""
    e = Errors.zeros(b, n_levels)

    def normal(*shape):
        return torch.randn(*shape, generator=gen, dtype=torch.float64)

    for s in sources:
        sig = spec.sigma(s)
        if s == "depth_scale":
            e.depth = sig * normal(b)
        elif s == "level_noise":
            if n_levels is None:
                e.roughness = torch.full((b,), sig, dtype=torch.float64)
            else:
                e.level = sig * normal(b, n_levels)
        elif s == "shift":
            e.dx, e.dy = sig * normal(b), sig * normal(b)
        elif s == "rotation":
            e.rotation = math.radians(sig) * normal(b)
        elif s == "wavelength":
            e.wavelength = sig * normal(b)
        elif s == "defocus":
            e.dz = sig * normal(b)
    return e


class PlateEvaluator:
    """LSR and mtf_mean of a plate under batches of errors, on the design's pupil grid and window.

    Args: plate; system: the design's OpticalSystem; material (the index at a detuned wavelength); band: the
    mtf_mean band; noise_gen: the generator of a continuous plate's roughness; batch: samples per propagation.
    """

    def __init__(self, plate: Plate, system: OpticalSystem, material: Material, band: tuple[float, float],
                 noise_gen: torch.Generator, batch: int):
        require_band_frequencies(system.spec, band)  # every sample's mtf_mean needs a frequency in the band
        self.plate, self.system, self.material, self.band = plate, system, material, band
        self.gen, self.batch = noise_gen, batch
        g = system.grid
        self.u = g.u.to(torch.float64).cpu()
        self.v = g.v.to(torch.float64).cpu()
        self.rho2 = (g.rho.to(torch.float64) ** 2).cpu()
        self._systems: dict[float, tuple[OpticalSystem, RadialMTF]] = {}

    def _system(self, wavelength_m: float) -> tuple[OpticalSystem, RadialMTF]:
        if wavelength_m not in self._systems:
            base = self.system
            system = base if wavelength_m == base.spec.wavelength_m else OpticalSystem(
                base.spec.replace(wavelength_m=wavelength_m), dtype=base.dtype, device=base.grid.rho.device,
                method=base.method)
            if len(self._systems) > 8:  # detuned systems are used once each
                self._systems.pop(next(k for k in self._systems if k != base.spec.wavelength_m))
            self._systems[wavelength_m] = (system, RadialMTF(system.spec, device=system.grid.rho.device))
        return self._systems[wavelength_m]

    def phases(self, e: Errors, wavelength_m: float) -> torch.Tensor:
        """The pupil phases (B, n, n) [rad], float64, of the plate under errors ``e`` at one wavelength."""
        b = len(e)
        c, s = torch.cos(e.rotation)[:, None, None], torch.sin(e.rotation)[:, None, None]
        uu = self.u[None, None, :] - e.dx[:, None, None]
        vv = self.v[None, :, None] - e.dy[:, None, None]
        pu, pv = c * uu + s * vv, c * vv - s * uu  # the pupil point in the plate's frame (rotated by -angle)
        h = self.plate.heights_at(pu, pv, e.level)
        if bool((e.roughness > 0).any()):
            n = self.rho2.shape[-1]
            h = h + e.roughness[:, None, None] * torch.randn(b, n, n, generator=self.gen, dtype=torch.float64)
        h = h * (1 + e.depth)[:, None, None]
        index = self.material.index(wavelength_m)
        f = self.system.spec.focal_length_m
        defocus = math.pi / (wavelength_m * f**2) * e.dz[:, None, None] * self.rho2[None]
        return phase_of_height(h, wavelength_m, index) + defocus

    @torch.no_grad()
    def __call__(self, e: Errors, progress: Callable[[int], None] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(lsr, mtf_mean), each (B,) float64, of every sample of ``e``."""
        lam0 = self.system.spec.wavelength_m
        lsr = torch.empty(len(e), dtype=torch.float64)
        mtf = torch.empty(len(e), dtype=torch.float64)
        lam = lam0 + e.wavelength
        same = (e.wavelength == 0).nonzero().squeeze(-1).tolist()
        groups = [(lam0, same[i:i + self.batch]) for i in range(0, len(same), self.batch)]
        groups += [(float(lam[i]), [i]) for i in (e.wavelength != 0).nonzero().squeeze(-1).tolist()]
        for wavelength, idx in groups:
            system, radial = self._system(wavelength)
            phase = self.phases(e.take(idx), wavelength).to(system.dtype).to(system.grid.rho.device)
            psf = system.psf(phase)
            lsr[idx] = metrics.lsr_sampled(psf, system.uncoded_peak).to(torch.float64).cpu()
            mean, _ = radial.summary(radial(metrics.mtf(psf)), self.band)
            mtf[idx] = mean.to(torch.float64).cpu()
            if progress is not None:
                progress(len(idx))
        return lsr, mtf


def deterministic(spec: ToleranceSpec, source: str, sign: float, n_levels: int | None) -> Errors | None:
    """One sample with ``source`` at ``sign`` x its sigma (the shift along u), None for level noise (random by
    nature: its spread is the Monte Carlo's)."""
    e = Errors.zeros(1, n_levels)
    sig = sign * spec.sigma(source)
    if source == "level_noise":
        return None
    if source == "depth_scale":
        e.depth[0] = sig
    elif source == "shift":
        e.dx[0] = sig
    elif source == "rotation":
        e.rotation[0] = math.radians(sig)
    elif source == "wavelength":
        e.wavelength[0] = sig
    elif source == "defocus":
        e.dz[0] = sig
    return e


register("tolerance", "default", spec_node(ToleranceSpec, seed="${seed}"))
