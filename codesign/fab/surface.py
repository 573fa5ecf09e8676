"""A design as a fabricated plate: its wrapped phase turned into surface heights in a material, optionally
quantized to K etch levels, on a square fabrication grid; and the plate seen again by the pupil grid, with the
plate shifted, rotated, its depth scaled or its levels perturbed (tolerance.py), at any wavelength.

Physics: a surface step h in a material of index n delays the wave by (n - 1) h, i.e. the phase
phi = 2 pi (n(lambda) - 1) h / lambda; a phase wrapped into [0, 2 pi) needs at most the full-wave depth
lambda / (n - 1). K levels: heights k lambda / (K (n - 1)), k = 0..K-1 (the nearest level modulo 2 pi, the same
rounding as a mask's ``levels``).

Fabrication grid: n_f x n_f square pixels at pitch p_f; pixel centres at (i - n_f // 2) p_f, so pixel n_f // 2 lies
on the optical axis (the pupil grid's convention), row = v, column = u. The plate is constant over each pixel; the
pupil grid reads it by nearest pixel (its samples are point samples of the surface). Outside the aperture's
support the height is 0 (the stop blocks that light).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from codesign.config.store import register, spec_node
from codesign.errors import ConfigError, require_number, round_down, round_up
from codesign.optics.grid import PupilGrid
from codesign.optics.lines import surface_phase
from codesign.optics.spec import OpticsSpec
from codesign.spec_base import SpecMixin

TWO_PI = 2 * math.pi
MAX_FAB_N = 8192  # a 8192^2 float64 height map is 0.5 GB, and the design's phase on it several times that


def height_of_phase(phase, wavelength_m: float, index: float):
    """Surface height [m] that delays by ``phase`` [rad]: phase lambda / (2 pi (n - 1))."""
    return phase * (wavelength_m / (TWO_PI * (index - 1)))


def phase_of_height(height, wavelength_m: float, index: float):
    """Phase [rad] of a surface height [m]: 2 pi (n - 1) h / lambda (the inverse of ``height_of_phase``)."""
    return height * (TWO_PI * (index - 1) / wavelength_m)


def wrap_phase(phase: torch.Tensor) -> torch.Tensor:
    """``phase`` modulo 2 pi, in [0, 2 pi)."""
    return surface_phase(phase, 1)


def level_index(wrapped: torch.Tensor, levels: int) -> torch.Tensor:
    """The nearest of ``levels`` equally spaced phases k 2 pi / K to a wrapped phase, modulo 2 pi (int64, 0..K-1)."""
    return torch.remainder(torch.round(wrapped / (TWO_PI / levels)).to(torch.int64), levels)


@dataclass(frozen=True)
class ExportSpec(SpecMixin):
    """pitch_m: fabrication pixel pitch [m] (a laser writer's or e-beam's address grid; 2 um by default);
    size_m: side of the square plate [m], null = the aperture's support plus one pixel each side; levels: number
    of etch levels K (2..256), null = continuous (grayscale lithography, diamond turning)."""

    pitch_m: float = 2e-6
    size_m: float | None = None
    levels: int | None = None
    prefix: str = field(default="export", compare=False, repr=False)

    def __post_init__(self) -> None:
        p = self.prefix
        require_number(f"{p}.pitch_m", self.pitch_m, lo=1e-8, hi=1e-3)
        if self.size_m is not None:
            require_number(f"{p}.size_m", self.size_m, lo=0, lo_open=True, hi=1.0)
        if self.levels is not None:
            object.__setattr__(self, "levels", require_number(f"{p}.levels", self.levels, lo=2, hi=256,
                                                              integer=True))

    def plate_n(self, optics: OpticsSpec) -> int:
        """Pixels per side of the plate; ConfigError when it cannot hold the aperture or is too large."""
        support = 2 * optics.aperture_support_radius_m
        need = math.ceil(support / self.pitch_m) + 2
        need += need % 2
        n = need if self.size_m is None else int(round(self.size_m / self.pitch_m))
        if n < need:
            raise ConfigError(f"{self.prefix}.size_m", self.size_m,
                              f"the plate must hold the aperture's support ({support:.4g} m): must be >= "
                              f"{need * self.pitch_m:.4g} m at {self.prefix}.pitch_m = {self.pitch_m:g}, or null")
        if n > MAX_FAB_N:
            raise self._too_large(n, support, need)
        return n

    def _too_large(self, n: int, support: float, need: int) -> ConfigError:
        """The error of a plate of more than MAX_FAB_N pixels per side, with advice true for these values: the
        pitch that brings it within the limit (for the size asked, or the aperture's support when size_m is null),
        rounded up, and the largest size at this pitch, rounded down (the old advice named support / 8190 even
        when size_m set the size: export.size_m=0.5 asked for a pitch the current one already met)."""
        p = self.prefix
        if self.size_m is None:  # n = ceil(support / pitch) + 2, made even: <= MAX_FAB_N from support / (MAX - 2) on
            return ConfigError(f"{p}.pitch_m", self.pitch_m, f"gives a plate of {n} x {n} pixels (the aperture's "
                               f"support, {support:.4g} m); at most {MAX_FAB_N} per side: raise {p}.pitch_m to >= "
                               f"{round_up(support / (MAX_FAB_N - 2)):.3g} m")
        # n = round(size / pitch) <= MAX_FAB_N from pitch = size / MAX_FAB_N on; a smaller size must still hold the
        # support (need pixels)
        most = round_down(MAX_FAB_N * self.pitch_m, 4)
        smaller = f" or lower {p}.size_m to <= {most:.4g} m" if most >= need * self.pitch_m else ""
        return ConfigError(f"{p}.size_m", self.size_m, f"gives a plate of {n} x {n} pixels at {p}.pitch_m = "
                           f"{self.pitch_m:g} m; at most {MAX_FAB_N} per side: raise {p}.pitch_m to >= "
                           f"{round_up(self.size_m / MAX_FAB_N):.3g} m{smaller}")


def fab_grid(optics: OpticsSpec, pitch_m: float, n: int) -> PupilGrid:
    """The pupil grid of the design's optics at the fabrication pitch and size (float64): the design's phase is
    evaluated there exactly for every family (a pixel family's plate is resampled cell by cell)."""
    spec = optics.replace(pupil_pitch_m=pitch_m, pupil_n=n, focal_n=8, focal_pitch_m=optics.focal_pitch_m,
                          propagator="mft", fft_n=None, laser_wavelengths_m=None, scene_spectrum=None)
    return PupilGrid.from_spec(spec, dtype=torch.float64)


@dataclass
class Plate:
    """A fabricated phase plate. height: (n, n) float64 heights [m]; levels: (n, n) int64 level indices or None
    (continuous); inside: (n, n) bool, the aperture's support; pitch [m]; wavelength_m and index: the design
    wavelength and the material's index there; wrap_waves: the wrap's depth in waves (None: not wrapped)."""

    height: torch.Tensor
    levels: torch.Tensor | None
    n_levels: int | None
    inside: torch.Tensor
    pitch: float
    wavelength_m: float
    index: float
    wrap_waves: int | None = 1

    @classmethod
    def from_phase(cls, phase: torch.Tensor, grid: PupilGrid, wavelength_m: float, index: float,
                   n_levels: int | None, wrap_waves: int | None) -> "Plate":
        """The plate of a design phase [rad] on the fabrication grid ``grid``: wrapped at 2 pi ``wrap_waves`` (1:
        the usual plate, m > 1: a multi-order plate, None: the continuous surface, its lowest point at height 0),
        quantized to ``n_levels`` over the wrap's depth when given, as heights."""
        inside = torch.zeros(grid.n * grid.n, dtype=torch.bool, device=phase.device)
        inside[grid.support] = True
        inside = inside.reshape(grid.n, grid.n)
        phase = phase.to(torch.float64)
        if wrap_waves is None:
            if n_levels is not None:
                raise ValueError("a continuous surface (wrap_waves None) has no etch levels")
            surface = phase - phase[inside].min() if bool(inside.any()) else phase
        else:
            surface = surface_phase(phase, wrap_waves)
        levels = None
        if n_levels is not None:
            levels = torch.where(inside, level_index(surface / wrap_waves, n_levels),
                                 torch.zeros_like(surface, dtype=torch.int64))
            surface = levels.to(torch.float64) * (TWO_PI * wrap_waves / n_levels)
        height = torch.where(inside, height_of_phase(surface, wavelength_m, index), torch.zeros_like(surface))
        return cls(height, levels, n_levels, inside, grid.pitch, wavelength_m, index, wrap_waves)

    @property
    def n(self) -> int:
        """The plate's samples across (its height map is n x n)."""
        return self.height.shape[-1]

    @property
    def full_wave_depth_m(self) -> float:
        """The depth of a 2 pi step at the design wavelength: lambda / (n - 1)."""
        return self.wavelength_m / (self.index - 1)

    @property
    def depth_m(self) -> float:
        """The depth range of the surface: wrap_waves full waves, or the continuous surface's highest point."""
        if self.wrap_waves is None:
            return max(float(self.height.max()), self.full_wave_depth_m)
        return self.wrap_waves * self.full_wave_depth_m

    @property
    def step_m(self) -> float | None:
        """Height of one etch level, or None for a continuous plate."""
        return None if self.n_levels is None else self.depth_m / self.n_levels

    def pixel_index(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Flat index of the plate pixel under plate coordinates (u, v) [m] (nearest pixel; clamped to the plate,
        whose border pixels lie outside the aperture)."""
        c = self.n // 2
        col = torch.round(u / self.pitch).to(torch.int64) + c
        row = torch.round(v / self.pitch).to(torch.int64) + c
        return row.clamp(0, self.n - 1) * self.n + col.clamp(0, self.n - 1)

    def heights_at(self, u: torch.Tensor, v: torch.Tensor, level_error: torch.Tensor | None = None) -> torch.Tensor:
        """Heights [m] at plate coordinates (..., k) (nearest pixel). ``level_error``: (B, K) height errors [m] of
        each level (B samples), added to the pixels of that level (a quantized plate only)."""
        idx = self.pixel_index(u, v)
        h = self.height.reshape(-1)[idx]
        if level_error is not None:
            lv = self.levels.reshape(-1)[idx]
            h = h + torch.gather(level_error, -1, lv.reshape(lv.shape[0], -1)).reshape(lv.shape)
        return h

    def pupil_phase(self, grid: PupilGrid, wavelength_m: float | None = None, index: float | None = None,
                    dtype=torch.float32) -> torch.Tensor:
        """The phase (n, n) the pupil grid ``grid`` sees through the plate, perfectly aligned, at
        ``wavelength_m`` (default: the design's) in a material of index ``index`` there."""
        lam = self.wavelength_m if wavelength_m is None else wavelength_m
        n = self.index if index is None else index
        u = grid.u.to(torch.float64)[None, :].expand(grid.n, grid.n)
        v = grid.v.to(torch.float64)[:, None].expand(grid.n, grid.n)
        return phase_of_height(self.heights_at(u, v), lam, n).to(dtype)


class PlatePhase:
    """A fixed pupil phase seen through a plate, with the part of the Mask interface the figures of merit use
    (``phase()``, ``plate_cell_m``): the pupil samples are point samples of the plate's surface."""

    plate_cell_m = None
    kind = "plate"

    def __init__(self, phase: torch.Tensor):
        self._phase = phase

    def phase(self) -> torch.Tensor:
        """The fixed pupil phase [rad], (n, n)."""
        return self._phase


register("export", "default", spec_node(ExportSpec))
