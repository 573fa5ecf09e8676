"""The optical system's physical parameters (Table 1 of the paper) and its sampling, validated at construction.

All lengths in metres. The pupil grid is square with pitch ``pupil_pitch_m``; the focal window is a square of
``focal_n`` pixels at ``focal_pitch_m`` (the sensor pitch), centred on the optical axis.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from codesign.config.store import register, spec_node
from codesign.errors import ConfigError, require_choice, require_list, require_number
from codesign.spec_base import SpecMixin

PROPAGATORS = ("auto", "mft", "czt", "fft")

# The super-Gaussian aperture exp(-(4 rho^2 / W_a^2)^P) is below 1e-20 beyond this radius (in units of W_a / 2)
# for P = 50; fields beyond it are set to exactly zero, and the grid must hold it.
_APERTURE_TAIL = 1e-20


@dataclass(frozen=True)
class OpticsSpec(SpecMixin):
    """Physical and sampling parameters of the imaging system (SI units).

    Attributes:
        wavelength_m: wavelength lambda [m] (Table 1: 633 nm).
        focal_length_m: effective focal length f [m] (Table 1: 0.11 m).
        aperture_diameter_m: aperture diameter W_a [m] (Table 1: 3.83 mm).
        supergaussian_order: exponent P of A = exp(-(4 rho^2 / W_a^2)^P) (Sec. 3.1: 50).
        pupil_pitch_m: pupil sample pitch Delta_u [m]: 9.974 um = 384 samples across W_a, the coarsest sampling whose
            LSR is within 1 % of the converged float64 value (docs/optics.md); Table 1's 3.74 um (1024 across) is
            the optics=paper preset.
        pupil_n: pupil grid size in samples; None = the smallest even grid that holds the aperture.
        focal_pitch_m: focal-plane sample pitch [m], the sensor pitch (Table 1: 5.4 um).
        focal_n: focal window size in samples (centred on the axis).
        propagator: "mft" (matrix Fourier transform onto the window), "czt" (chirp-z transform onto the same
            window: the same sums by FFT convolutions), "fft" (zero-padded FFT, resampled onto the window if its
            native pitch differs), or "auto" (the cheapest exact one by modelled cost, propagation.modelled_costs).
        fft_n: FFT size for the "fft" propagator (paper: 4096); None = the exact size when one exists, else the
            smallest fast size giving a native pitch <= focal_pitch / 2 (bilinear resampling then stays accurate).
        psf_file: a measured PSF that replaces the computed one (a 16-bit PNG / TIFF frame or a .npy array; None:
            the PSF is computed from the mask). Read, registered and resampled onto the window by
            codesign/optics/measured.py (docs/measured_psf.md); the files are checked there, not here.
        psf_pitch_m: the pixel pitch of ``psf_file`` at the sensor plane [m]; required with psf_file.
        psf_dark_file: a dark frame subtracted from ``psf_file`` (same kind and size), or None.
        psf_energy: the fraction of all the light through the aperture that the ``psf_file`` frame holds (the frame
            is normalized to it; 1 = all of it; the computed window PSF holds psf_energy_in_window).
        psf_centre: where the measured frame's centroid goes: "design" (the design mask's computed PSF's centroid),
            "centroid" (the optical axis) or "frame" (no shift: the frame's centre pixel is the axis).
        laser_wavelengths_m: the laser lines the mask must protect against [m] (a list; None = the design
            wavelength alone). The mask is made for ``wavelength_m`` in the configured ``material.*``; a line
            lambda sees its surface with the phase 2 pi (n(lambda) - 1) h / lambda (codesign/optics/lines.py).
        wrap_waves: how the surface is made: the design phase wrapped at 2 pi wrap_waves (1 = the usual
            diffractive plate, m > 1 = a multi-order plate m waves deep) or None = the continuous (unwrapped)
            surface. The same phase at the design wavelength; off it the wrap's steps are no longer whole waves.
        scene_spectrum: the scene's light as a few samples of its band, a list of [wavelength_m, weight] pairs
            (None = the design wavelength alone): the scene's PSF is the weighted mean of the mask's PSFs at those
            wavelengths (the surface seen at each), in simulation, training and restoration; the laser stays at
            its line.
    """

    wavelength_m: float = 633e-9
    focal_length_m: float = 0.11
    aperture_diameter_m: float = 3.83e-3
    supergaussian_order: float = 50.0
    pupil_pitch_m: float = 9.974e-6  # 3.83 mm / 384
    pupil_n: int | None = None
    focal_pitch_m: float = 5.4e-6
    focal_n: int = 640
    propagator: str = "auto"
    fft_n: int | None = None
    psf_file: str | None = None
    psf_pitch_m: float | None = None
    psf_dark_file: str | None = None
    psf_energy: float = 1.0
    psf_centre: str = "design"
    laser_wavelengths_m: tuple | None = None
    wrap_waves: int | None = 1
    scene_spectrum: tuple | None = None
    prefix: str = field(default="optics", compare=False, repr=False)

    def __post_init__(self) -> None:
        p = self.prefix
        require_number(f"{p}.wavelength_m", self.wavelength_m, lo=1e-8, hi=1e-4)
        require_number(f"{p}.focal_length_m", self.focal_length_m, lo=0, lo_open=True, hi=100)
        require_number(f"{p}.aperture_diameter_m", self.aperture_diameter_m, lo=0, lo_open=True, hi=10)
        require_number(f"{p}.supergaussian_order", self.supergaussian_order, lo=1, hi=1000)
        require_number(f"{p}.pupil_pitch_m", self.pupil_pitch_m, lo=0, lo_open=True)
        require_number(f"{p}.focal_pitch_m", self.focal_pitch_m, lo=0, lo_open=True)
        # Store validated integers (a YAML 640.0 is accepted as 640, and must then be an int everywhere).
        object.__setattr__(self, "focal_n", require_number(f"{p}.focal_n", self.focal_n, lo=8, hi=16384,
                                                           integer=True))
        require_choice(f"{p}.propagator", self.propagator, PROPAGATORS)
        need = self.min_pupil_n
        if self.pupil_n is not None:
            object.__setattr__(self, "pupil_n", require_number(f"{p}.pupil_n", self.pupil_n, lo=2, hi=65536,
                                                               integer=True))
            if self.pupil_n < need:
                raise ConfigError(
                    f"{p}.pupil_n", self.pupil_n,
                    f"the pupil grid ({self.pupil_n} x {self.pupil_pitch_m:.3g} m) cannot hold the aperture "
                    f"(W_a = {self.aperture_diameter_m:.4g} m with its super-Gaussian edge): must be >= {need}, "
                    f"or null for automatic")
        if self.fft_n is not None:
            object.__setattr__(self, "fft_n", require_number(f"{p}.fft_n", self.fft_n, lo=2, hi=65536,
                                                             integer=True))
            if self.fft_n < self.grid_n:
                raise ConfigError(f"{p}.fft_n", self.fft_n,
                                  f"must be >= the pupil grid size {self.grid_n} (or null for automatic)")
            native = self.lambda_f / (self.fft_n * self.pupil_pitch_m)
            if self.lambda_f_over_d / native < 2.0 or self.fft_n * native < self.focal_extent_m:
                need = math.ceil(max(2 * self.lambda_f / (self.pupil_pitch_m * self.lambda_f_over_d),
                                     self.grid_n))
                raise ConfigError(f"{p}.fft_n", self.fft_n,
                                  f"its native focal pitch {native:.3g} m would alias the PSF "
                                  f"({self.lambda_f_over_d / native:.3g} samples per lambda*f/W_a, need >= 2) or "
                                  f"its field is smaller than the window: must be >= {need}, or null")
        if self.samples_per_lambda_f_over_d < 2.0:
            raise ConfigError(
                f"{p}.focal_pitch_m", self.focal_pitch_m,
                f"the focal sampling would alias the intensity PSF: {self.samples_per_lambda_f_over_d:.3g} samples "
                f"per lambda*f/W_a, need >= 2, i.e. focal_pitch_m <= {self.lambda_f_over_d / 2:.4g} m")
        if self.focal_extent_m > self.replica_period_m * (1 + 1e-9):
            raise ConfigError(
                f"{p}.pupil_pitch_m", self.pupil_pitch_m,
                f"the focal window ({self.focal_n} x {self.focal_pitch_m:.3g} m = {self.focal_extent_m:.4g} m) is "
                f"wider than the period lambda*f/pupil_pitch = {self.replica_period_m:.4g} m of the sampled pupil's "
                f"spectrum, so it would alias: need pupil_pitch_m <= "
                f"{self.wavelength_m * self.focal_length_m / self.focal_extent_m:.4g} m or a smaller focal_n")
        self._check_measured()
        self._check_lines()
        self._check_spectrum()

    def _check_lines(self) -> None:
        """The laser lines: each a wavelength the window neither aliases nor undersamples on this pupil grid."""
        p = self.prefix
        if self.wrap_waves is not None:
            object.__setattr__(self, "wrap_waves", require_number(f"{p}.wrap_waves", self.wrap_waves, lo=1, hi=1000,
                                                                  integer=True))
        if self.laser_wavelengths_m is None:
            return
        allowed = ("must be null (the design wavelength alone) or a list of laser wavelengths in m, e.g. "
                   "[4.5e-7, 5.32e-7, 6.33e-7]")
        lines = require_list(f"{p}.laser_wavelengths_m", self.laser_wavelengths_m, allowed)
        if not lines:
            raise ConfigError(f"{p}.laser_wavelengths_m", self.laser_wavelengths_m, allowed)
        out = []
        for i, lam in enumerate(lines):
            key = f"{p}.laser_wavelengths_m[{i}]"
            lam = require_number(key, lam, lo=1e-8, hi=1e-4)
            problem = self.line_problem(lam)
            if problem is not None:
                raise ConfigError(key, lam, problem)
            out.append(float(lam))
        if len(set(out)) != len(out):
            raise ConfigError(f"{p}.laser_wavelengths_m", lines, "names a line twice")
        object.__setattr__(self, "laser_wavelengths_m", tuple(out))

    def _check_spectrum(self) -> None:
        """The scene's spectrum: [wavelength_m, weight] pairs, each wavelength one the window can carry."""
        p, key = self.prefix, f"{self.prefix}.scene_spectrum"
        if self.scene_spectrum is None:
            return
        allowed = ("must be null (the design wavelength alone) or a list of [wavelength_m, weight] pairs, weights "
                   "> 0, e.g. [[4.5e-7, 1], [5.5e-7, 2], [6.33e-7, 1]]")
        pairs = require_list(key, self.scene_spectrum, allowed)
        if not pairs:
            raise ConfigError(key, self.scene_spectrum, allowed)
        out = []
        for i, pair in enumerate(pairs):
            pair = require_list(f"{key}[{i}]", pair, allowed)
            if len(pair) != 2:
                raise ConfigError(f"{key}[{i}]", pair, allowed)
            lam = require_number(f"{key}[{i}][0]", pair[0], lo=1e-8, hi=1e-4)
            weight = require_number(f"{key}[{i}][1]", pair[1], lo=0, lo_open=True, hi=1e12)
            problem = self.line_problem(lam)
            if problem is not None:
                raise ConfigError(f"{key}[{i}][0]", lam, problem.replace("this line", "this wavelength"))
            out.append((float(lam), float(weight)))
        if len({w for w, _ in out}) != len(out):
            raise ConfigError(key, pairs, f"names a wavelength twice ({p}.scene_spectrum sums the samples' weights)")
        object.__setattr__(self, "scene_spectrum", tuple(out))

    def line_problem(self, wavelength_m: float) -> str | None:
        """Why this pupil grid and window cannot carry a laser line's PSF (aliasing), or None when they can."""
        p = self.prefix
        period = wavelength_m * self.focal_length_m / self.pupil_pitch_m
        if self.focal_extent_m > period * (1 + 1e-9):
            return (f"at this line the sampled pupil's spectrum repeats every lambda f / pupil_pitch = {period:.4g} m, "
                    f"less than the {self.focal_extent_m:.4g} m window: its PSF would alias; need {p}.pupil_pitch_m "
                    f"<= {wavelength_m * self.focal_length_m / self.focal_extent_m:.4g} m, a smaller {p}.focal_n, or "
                    f"a longer line")
        samples = wavelength_m * self.focal_length_m / self.aperture_diameter_m / self.focal_pitch_m
        if samples < 2.0:
            return (f"the sensor's pitch {p}.focal_pitch_m = {self.focal_pitch_m:g} m samples this line's PSF at "
                    f"{samples:.3g} samples per lambda f / W_a, below the 2 it needs: the line is too short for this "
                    f"sensor (a longer one, or a smaller {p}.aperture_diameter_m)")
        return None

    def is_design_wavelength(self, wavelength_m: float) -> bool:
        """Whether ``wavelength_m`` is the design wavelength (to 1e-12 relative: a value typed in another form)."""
        return abs(wavelength_m - self.wavelength_m) <= 1e-12 * self.wavelength_m

    @property
    def laser_lines(self) -> tuple[float, ...]:
        """The laser wavelengths [m]: laser_wavelengths_m, or the design wavelength alone."""
        return self.laser_wavelengths_m or (self.wavelength_m,)

    def _check_measured(self) -> None:
        """The measured-PSF keys' values (their files are read and checked by codesign/optics/measured.py)."""
        p = self.prefix
        for key in ("psf_file", "psf_dark_file"):
            value = getattr(self, key)
            if value is not None and (not isinstance(value, str) or not value.strip()):
                raise ConfigError(f"{p}.{key}", value, "must be null or the path of a file (a measured PSF is a "
                                  "16-bit PNG / TIFF frame or a .npy array of floats)")
        if self.psf_file is None:
            for key in ("psf_pitch_m", "psf_dark_file"):
                if getattr(self, key) is not None:
                    raise ConfigError(f"{p}.{key}", getattr(self, key), f"describes {p}.psf_file, which is null: "
                                      f"give the measured PSF with {p}.psf_file=PATH, or leave {p}.{key} null")
        elif self.psf_pitch_m is None:
            raise ConfigError(f"{p}.psf_pitch_m", None, f"pitch missing: the pixel pitch of {p}.psf_file at the "
                              f"sensor plane in m is needed to resample it onto the optics window, e.g. "
                              f"{p}.psf_pitch_m={self.focal_pitch_m:g} for a frame taken with the sensor itself")
        if self.psf_pitch_m is not None:
            object.__setattr__(self, "psf_pitch_m", require_number(f"{p}.psf_pitch_m", self.psf_pitch_m, lo=0,
                                                                   lo_open=True, hi=1e-2))
        object.__setattr__(self, "psf_energy", require_number(f"{p}.psf_energy", self.psf_energy, lo=0,
                                                              lo_open=True, hi=1))
        require_choice(f"{p}.psf_centre", self.psf_centre, ("design", "centroid", "frame"))
        if self.psf_file is None and self.psf_energy != 1.0:  # it scales the measured frame alone: was ignored
            raise ConfigError(f"{p}.psf_energy", self.psf_energy, f"describes {p}.psf_file, which is null: give the "
                              f"measured PSF with {p}.psf_file=PATH, or leave {p}.psf_energy at 1 (the default)")

    # ---- derived quantities -------------------------------------------------------------------------------
    @property
    def lambda_f(self) -> float:
        """lambda * f [m^2]: the Fourier scale between pupil and focal coordinates."""
        return self.wavelength_m * self.focal_length_m

    @property
    def lambda_f_over_d(self) -> float:
        """lambda f / W_a [m]; the Airy first zero is at 1.22 times this."""
        return self.lambda_f / self.aperture_diameter_m

    @property
    def samples_per_lambda_f_over_d(self) -> float:
        """Focal samples per lambda f / D (the diffraction-limited spot's scale)."""
        return self.lambda_f_over_d / self.focal_pitch_m

    @property
    def aperture_support_radius_m(self) -> float:
        """Radius beyond which the super-Gaussian aperture is < 1e-20 (treated as exactly zero)."""
        return 0.5 * self.aperture_diameter_m * (-math.log(_APERTURE_TAIL)) ** (0.5 / self.supergaussian_order)

    @property
    def min_pupil_n(self) -> int:
        """The smallest even pupil grid that holds the aperture support with a sample to spare on each side."""
        n = math.ceil(2 * self.aperture_support_radius_m / self.pupil_pitch_m) + 2
        return n + n % 2

    @property
    def grid_n(self) -> int:
        """The pupil grid's samples across: pupil_n, or min_pupil_n when it is null."""
        return self.pupil_n if self.pupil_n is not None else self.min_pupil_n

    @property
    def samples_across_aperture(self) -> float:
        """Pupil samples across the aperture diameter (W_a / pupil pitch)."""
        return self.aperture_diameter_m / self.pupil_pitch_m

    @property
    def focal_extent_m(self) -> float:
        """The focal window's width [m]: focal_n x focal_pitch_m."""
        return self.focal_n * self.focal_pitch_m

    @property
    def replica_period_m(self) -> float:
        """lambda f / Delta_u: the focal-plane period of the sampled pupil's Fourier transform."""
        return self.lambda_f / self.pupil_pitch_m

    @property
    def cutoff_frequency(self) -> float:
        """Incoherent cutoff W_a / (lambda f) [cycles/m]."""
        return self.aperture_diameter_m / self.lambda_f

    # ---- construction (replace, from_config: SpecMixin) ---------------------------------------------------
    @classmethod
    def with_samples_across(cls, samples: float, **kw: Any) -> "OpticsSpec":
        """The spec whose pupil pitch puts ``samples`` pupil samples across the aperture diameter."""
        d = kw.get("aperture_diameter_m", cls.aperture_diameter_m)
        return cls(pupil_pitch_m=d / samples, **kw)


register("optics", "default", spec_node(OpticsSpec))
