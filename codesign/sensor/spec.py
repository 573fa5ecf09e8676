"""Sensor parameters (Table 1) and the simulation geometry, validated at construction. SI units, electrons e-."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from codesign.config.store import register, spec_node
from codesign.errors import ConfigError, require_choice, require_number
from codesign.spec_base import SpecMixin

PLANCK_J_S = 6.62607015e-34
LIGHT_M_S = 299792458.0
PATHS = ("direct", "full")
DOWNSAMPLERS = ("area", "bicubic_aa")
BIT_DEPTHS = (8, 24)  # the ADC resolutions of real image sensors (8-16 bit; scientific cameras up to 24)


@dataclass(frozen=True)
class SensorSpec(SpecMixin):
    """Sensor of Table 1 plus how it is simulated.

    Attributes:
        wavelength_background_m, wavelength_laser_m: lambda_b, lambda_l [m].
        exposure_s: default exposure t [s] (scenes may carry their own).
        quantum_efficiency: Q_e; gain_dn_per_e: G [DN/e-]; full_well_e: e_sat [e-]; bit_depth: bpc.
        read_noise_mean_e, read_noise_std_e: mu_r, sigma_r [e-]; dark_current_mean_e: mu_c [e- per exposure].
        pixel_pitch_m: sensor pitch Delta_x [m]; resolution: sensor pixels per side (the paper's 2532 crop).
        image_size: network resolution (the sensor is simulated or binned to image_size x image_size);
        padded_size: network input size after zero padding (Sec. 6.2: 256 -> 384).
        path: "direct" (simulate at the network resolution with the PSF integrated over the coarse pixel) or
            "full" (simulate at sensor resolution, then downsample with ``downsample``).
        pixel_integration: integrate the PSF over the pixel (True) or point-sample it (False).
        background_veil: add the energy scattered beyond the optics window back as a uniform veil of the scene's
            mean (True), so that a uniform scene keeps its brightness through any phase mask (BSR = 1).
        laser_halo: add the laser's light beyond the optics window (True: the far PSF on a pupil grid fine enough
            for the whole sensor, codesign/sensor/halo.py), so that a strong laser saturates pixels far from its
            spot; False keeps only the window PSF (the light beyond it is dropped).
        halo_refresh: while the mask trains, the far PSF (no gradient, ~2-4 s on 2 cores) is recomputed every
            this many optics evaluations; a frozen mask computes it once.
    """

    wavelength_background_m: float = 633e-9
    wavelength_laser_m: float = 633e-9
    exposure_s: float = 0.1
    quantum_efficiency: float = 0.56
    gain_dn_per_e: float = 0.37
    full_well_e: float = 25500.0
    read_noise_mean_e: float = 390.0
    read_noise_std_e: float = 10.5
    dark_current_mean_e: float = 0.002
    bit_depth: int = 16
    pixel_pitch_m: float = 5.4e-6
    resolution: int = 2532
    image_size: int = 256
    padded_size: int = 384
    path: str = "direct"
    downsample: str = "area"
    pixel_integration: bool = True
    background_veil: bool = True
    laser_halo: bool = True
    halo_refresh: int = 25
    prefix: str = field(default="sensor", compare=False, repr=False)

    def __post_init__(self) -> None:
        p = self.prefix
        for key in ("wavelength_background_m", "wavelength_laser_m"):
            require_number(f"{p}.{key}", getattr(self, key), lo=1e-8, hi=1e-4)
        require_number(f"{p}.exposure_s", self.exposure_s, lo=1e-6, hi=1e3)
        require_number(f"{p}.quantum_efficiency", self.quantum_efficiency, lo=0, lo_open=True, hi=1)
        require_number(f"{p}.gain_dn_per_e", self.gain_dn_per_e, lo=0, lo_open=True)
        require_number(f"{p}.full_well_e", self.full_well_e, lo=0, lo_open=True)
        require_number(f"{p}.read_noise_mean_e", self.read_noise_mean_e, lo=0)
        require_number(f"{p}.read_noise_std_e", self.read_noise_std_e, lo=0)
        require_number(f"{p}.dark_current_mean_e", self.dark_current_mean_e, lo=0)
        require_number(f"{p}.pixel_pitch_m", self.pixel_pitch_m, lo=0, lo_open=True)
        for key, lo, hi in (("resolution", 8, 65536), ("image_size", 8, 65536), ("padded_size", 8, 65536)):
            object.__setattr__(self, key, require_number(f"{p}.{key}", getattr(self, key), lo=lo, hi=hi,
                                                         integer=True))
        self._check_bit_depth()
        if self.padded_size < self.image_size:
            raise ConfigError(f"{p}.padded_size", self.padded_size, f"must be >= {p}.image_size ({self.image_size})")
        if self.resolution < self.image_size:
            raise ConfigError(f"{p}.resolution", self.resolution,
                              f"must be >= {p}.image_size ({self.image_size}): the sensor is binned, never upsampled")
        require_choice(f"{p}.path", self.path, PATHS)
        require_choice(f"{p}.downsample", self.downsample, DOWNSAMPLERS)
        object.__setattr__(self, "halo_refresh", require_number(f"{p}.halo_refresh", self.halo_refresh, lo=1,
                                                                integer=True))
        for key in ("pixel_integration", "background_veil", "laser_halo"):
            if not isinstance(getattr(self, key), bool):
                raise ConfigError(f"{p}.{key}", getattr(self, key), "must be true or false")

    def _check_bit_depth(self) -> None:
        """bit_depth: what real sensors digitize with, and a full scale above the black level (the read-noise
        offset): a 1-bit sensor read every pixel as full scale (1 DN) and reported none of them saturated."""
        p, (lo, hi) = self.prefix, BIT_DEPTHS
        allowed = (f"must be an integer >= {lo} and <= {hi} (image sensors digitize with 8 to 16 bits, scientific "
                   f"cameras up to {hi})")
        try:
            bits = require_number(f"{p}.bit_depth", self.bit_depth, lo=lo, hi=hi, integer=True)
        except ConfigError:
            raise ConfigError(f"{p}.bit_depth", self.bit_depth, allowed) from None
        object.__setattr__(self, "bit_depth", bits)
        black = self.gain_dn_per_e * (self.read_noise_mean_e + self.dark_current_mean_e)
        if self.saturation_dn <= black:
            need = max(lo, math.floor(math.log2(black + 1)) + 1)
            raise ConfigError(f"{p}.bit_depth", bits, f"its full scale 2^{bits} - 1 = {self.saturation_dn:.0f} DN is "
                              f"not above the black level {black:.4g} DN ({p}.gain_dn_per_e x ({p}.read_noise_mean_e "
                              f"+ {p}.dark_current_mean_e)): every pixel would read full scale; need bit_depth >= "
                              f"{need}")

    # ---- derived -------------------------------------------------------------------------------------------
    @property
    def saturation_dn(self) -> float:
        """s_sat = 2^bpc - 1."""
        return float(2**self.bit_depth - 1)

    @property
    def bin_factor(self) -> float:
        """Sensor pixels per network pixel along one side (2532 / 256 = 9.89)."""
        return self.resolution / self.image_size

    @property
    def side_m(self) -> float:
        """Side of the (square) simulated sensor crop, W_s = H_s = resolution x pitch [m]."""
        return self.resolution * self.pixel_pitch_m

    @property
    def coarse_pitch_m(self) -> float:
        """The network pixel's pitch [m]: the sensor pixel pitch times bin_factor."""
        return self.pixel_pitch_m * self.bin_factor

    def saturation_irradiance(self, wavelength_m: float, exposure_s: float | None = None) -> float:
        """I_sat = e_sat h c / (lambda t dx^2 Q_e) [W/m^2], Eq. (ThresSat)."""
        t = self.exposure_s if exposure_s is None else exposure_s
        return self.full_well_e * PLANCK_J_S * LIGHT_M_S / (
            wavelength_m * t * self.pixel_pitch_m**2 * self.quantum_efficiency)

    def photons_per_joule(self, wavelength_m: float) -> float:
        """lambda / (h c): photons per joule at ``wavelength_m`` (Eq. photon_count)."""
        return wavelength_m / (PLANCK_J_S * LIGHT_M_S)



def kernel_size(extent_m: float, pitch_m: float) -> int:
    """Odd number of samples at ``pitch_m`` that covers ``extent_m`` (the PSF support)."""
    n = math.ceil(extent_m / pitch_m)
    return n + (1 - n % 2)


# the network resolution (image_size, padded_size) is data.*: not a sensor key a user types
register("sensor", "default", spec_node(SensorSpec, drop=("image_size", "padded_size")))
