"""The one mask interface: a module with a differentiable ``phase()`` on its pupil grid, its free parameters as one
vector with bounds, a ``project()`` onto what can be built, and a JSON record that rebuilds it.

A mask family is one module of this package: a ``Mask`` subclass with a ``kind`` (its name in ``mask.kind`` and in
records) and a ``Spec`` dataclass (its config keys and their defaults, the single source of both). Importing
``codesign.optics.masks`` registers every family; ``build_mask`` builds any of them from a config mapping.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, Mapping

import torch

from codesign.errors import ConfigError, require_choice, require_number
from codesign.optics.grid import PupilGrid
from codesign.spec_base import SpecMixin

FAMILIES: dict[str, type["Mask"]] = {}
# the bound [rad] of a phase value a record holds (pixel values, spline controls, Zernike coefficients): 100 times
# the config's bound on a phase (defocus_rad, the search boxes: 1e4), so that every phase a config makes is accepted
# (the corner controls of a spline, outside the aperture, reach 2.5e4 for the largest defocus, 8e5 with the coarsest
# control spacing) and a meaningless 1e30 is refused
PHASE_LIMIT = 1e6


def require_levels(key: str, value: Any) -> int | None:
    """``levels``: null (continuous) or an integer in [2, 65536], as mask.levels and a record's levels."""
    return None if value is None else require_number(key, value, lo=2, hi=65536, integer=True)


def require_phases(key: str, values: list) -> None:
    """Every value of a record's list of phases [rad] within +-PHASE_LIMIT (the first one outside named as
    ``key[i]``); a fast pass first: a pixel record holds 10^5 values."""
    if all(-PHASE_LIMIT <= v <= PHASE_LIMIT for v in values):
        return
    for i, v in enumerate(values):
        require_number(f"{key}[{i}]", v, lo=-PHASE_LIMIT, hi=PHASE_LIMIT)


@dataclass(frozen=True)
class MaskSpec(SpecMixin):
    """Keys every family has. kind: the family; init: a mask record to start from (JSON written by mask_search,
    joint or psf; any family's record: a different family is fitted to its phase where the family can be);
    levels: quantize the phase to this many levels in [-pi, pi) (a buildable multi-level plate; the gradient passes
    straight through), null = continuous."""

    kind: str = ""
    init: str | None = None
    levels: int | None = None
    prefix: str = field(default="mask", compare=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "levels", require_levels(f"{self.prefix}.levels", self.levels))

    @classmethod
    def defaults(cls) -> dict:
        """The config node of the family: every key with its default (lists for tuples)."""
        out = {}
        for f in fields(cls):
            if f.name == "prefix":
                continue
            v = f.default
            out[f.name] = list(v) if isinstance(v, tuple) else v
        return out


# the named starts of the families that fit any phase (``Mask.fits_phases``): mask.init=published|zero|defocus
NAMED_STARTS = ("published", "zero", "defocus")


@dataclass(frozen=True)
class PhaseFitSpec(MaskSpec):
    """Keys of the families that can start from any phase (``Mask.fits_phases``). init_convention: the published
    half-ring phase a ``published`` start takes (atan | atan2); defocus_rad: the strength of a ``defocus`` start,
    phi = defocus_rad (rho / R)^2 [rad at the aperture edge] (a near flat-top PSF: the best start of a search)."""

    init_convention: str = "atan2"
    defocus_rad: float = 40.0

    def __post_init__(self) -> None:
        super().__post_init__()
        require_choice(f"{self.prefix}.init_convention", self.init_convention, ("atan", "atan2"))
        require_number(f"{self.prefix}.defocus_rad", self.defocus_rad, lo=-1e4, hi=1e4)


def fill_outside(ph: torch.Tensor, grid: PupilGrid) -> torch.Tensor:
    """The phase with every sample outside the support set to its nearest support sample's (along rows, then
    columns, repeatedly): interpolation near the aperture edge then never mixes in the zeros outside."""
    inside = torch.zeros(grid.n * grid.n, dtype=torch.bool, device=ph.device)
    inside[grid.support] = True
    inside = inside.reshape(grid.n, grid.n)
    out = ph.clone()
    filled = inside.clone()
    for _ in range(grid.n):
        if bool(filled.all()):
            break
        grown = filled.clone()
        for dim, step in ((0, 1), (0, -1), (1, 1), (1, -1)):
            src_ok = torch.roll(filled, step, dims=dim)
            take = ~grown & src_ok
            out = torch.where(take, torch.roll(out, step, dims=dim), out)
            grown = grown | take
        filled = grown
    return out


def quantize(phase: torch.Tensor, levels: int) -> torch.Tensor:
    """``phase`` wrapped into [-pi, pi) and rounded to ``levels`` equally spaced values there; the gradient is the
    identity (straight-through), so that search and co-design can move a quantized mask's parameters."""
    step = 2 * math.pi / levels
    wrapped = torch.remainder(phase + math.pi, 2 * math.pi) - math.pi
    q = torch.round(wrapped / step) * step
    q = torch.where(q >= math.pi, q - 2 * math.pi, q)
    return phase + (q - phase).detach()


class Mask(torch.nn.Module):
    """Base class of every pupil phase mask.

    Subclasses hold their learnable parameters and implement ``support_phase()``: the phase [rad] at the grid's
    support samples, shape (n_support,). ``phase()`` places it on the full (n, n) grid (0 outside the aperture,
    where the field is exactly zero anyway), quantized when ``levels`` is set. ``project()`` clamps the parameters,
    in place and without autograd, to what can be built; the trainer and the search call it after each update.
    """

    kind: ClassVar[str] = ""
    Spec: ClassVar[type[MaskSpec]] = MaskSpec
    # what a search of this family uses by default: the floor on the PSF energy kept in the optics window, and the
    # cap on the phase step between neighbouring pupil samples (None: no cap)
    design_energy_floor: ClassVar[str | float] = 0.98
    resolution_step: ClassVar[float | None] = None
    fits_phases: ClassVar[bool] = False  # fit_phase works: any phase can start it (random starts: defocus), and
    # mask.init takes the NAMED_STARTS and any family's record (fitted)
    # what a record of the family holds (mask.init reads it back): its parameter values, name -> "list" (a non-empty
    # list of numbers) or "number", and its settings besides its Spec's keys (Mask.settings())
    record_values: ClassVar[dict[str, str]] = {}
    record_settings: ClassVar[tuple[str, ...]] = ()
    # start 0 of a search with search.init=auto: published (the published mask in this family), mask (the
    # configured one) or defocus (a near flat-top PSF, for the families that fit any phase)
    search_start: ClassVar[str] = "published"
    # the design check's finer pupil grid: pitch / fine_factor (2; the pixel family's cells split exactly into 3 x 3)
    fine_factor: ClassVar[int] = 2

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if cls.kind:
            FAMILIES[cls.kind] = cls

    def __init__(self, grid: PupilGrid, levels: int | None = None):
        super().__init__()
        self.grid = grid
        self.levels = require_levels("mask.levels", levels)

    # ---- the phase ------------------------------------------------------------------------------------------------
    @property
    def plate_cell_m(self) -> float | None:
        """Width [m] of the square cells over which the phase is constant (a pixelated plate: its PSF takes the
        cells' sinc envelope, OpticalSystem.psf), or None: the pupil samples are point samples of a smooth surface."""
        return None

    def support_phase(self) -> torch.Tensor:  # pragma: no cover - abstract
        """The phase [rad] at the grid's support samples, shape (n_support,): what each family implements."""
        raise NotImplementedError

    def phase(self) -> torch.Tensor:
        """Pupil phase [rad], shape (n, n), on the grid's dtype/device."""
        values = self.support_phase()
        if self.levels is not None:
            values = quantize(values, self.levels)
        return self.grid.scatter(values)

    def forward(self) -> torch.Tensor:
        """``mask()`` is ``mask.phase()``, so torch.func.functional_call can evaluate a mask at given parameters."""
        return self.phase()

    @torch.no_grad()
    def project(self) -> None:
        """Clamp parameters to the buildable set (default: nothing to clamp)."""

    def freeze(self) -> "Mask":
        """Stop every parameter's gradient (a fixed mask: a reference, a re-check, an exported design); returns the
        mask."""
        for p in self.parameters():
            p.requires_grad_(False)
        return self

    # ---- the parameter vector (searches) ------------------------------------------------------------------------
    def to_vector(self) -> torch.Tensor:
        """Every free parameter, flattened in ``parameters()`` order, float64 on the CPU."""
        return torch.cat([p.detach().reshape(-1).to(torch.float64).cpu() for p in self.parameters()])

    @torch.no_grad()
    def set_vector(self, x) -> None:
        """Write a vector (``to_vector`` layout) into the parameters."""
        x = torch.as_tensor(x, dtype=torch.float64).reshape(-1)
        if x.numel() != self.vector_size:
            raise ValueError(f"a {self.kind} mask has {self.vector_size} parameters, got a vector of {x.numel()}")
        at = 0
        for p in self.parameters():
            p.copy_(x[at:at + p.numel()].view_as(p).to(p))
            at += p.numel()

    def vector_grad(self) -> torch.Tensor:
        """The parameters' gradients in ``to_vector`` layout (zeros where a parameter has none)."""
        return torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).detach().reshape(-1)
                          .to(torch.float64).cpu() for p in self.parameters()])

    @property
    def vector_size(self) -> int:
        """The number of free parameters: the length of ``to_vector()``."""
        return sum(p.numel() for p in self.parameters())

    def bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(lower, upper) of every parameter in ``to_vector`` layout (float64): the box a search stays in."""
        n = self.vector_size
        return torch.full((n,), -math.inf, dtype=torch.float64), torch.full((n,), math.inf, dtype=torch.float64)

    def fit_phase(self, phase: torch.Tensor) -> None:
        """Set the parameters so that the mask's phase approximates a full-grid (n, n) phase (families that can
        represent any phase: pixel, spline, Zernike)."""
        raise NotImplementedError(f"a {self.kind} mask cannot be fitted to an arbitrary phase")

    @torch.no_grad()
    def random_vector(self, rng) -> torch.Tensor:
        """A random start for searches (``rng``: numpy Generator): uniform in the bounds; families that fit a phase
        take a defocus of random strength in [25, 55] rad (a near flat-top PSF: the good starts)."""
        if self.fits_phases:
            return self.defocus_vector(float(rng.uniform(25.0, 55.0)))
        lo, hi = self.bounds()
        return lo + (hi - lo) * torch.from_numpy(rng.random(lo.numel()))

    def defocus_vector(self, strength_rad: float) -> torch.Tensor:
        """The parameter vector of a defocus phase, ``strength_rad`` (rho / rho_max)^2 (families that fit a
        phase)."""
        radius = float(self.grid.rho.reshape(-1)[self.grid.support].max())
        return self.phase_vector(strength_rad * (self.grid.rho / radius) ** 2)

    @torch.no_grad()
    def phase_vector(self, phase: torch.Tensor) -> torch.Tensor:
        """The parameter vector whose phase approximates ``phase`` (``fit_phase``), the mask left unchanged."""
        keep = self.to_vector()
        self.fit_phase(phase)
        out = self.to_vector()
        self.set_vector(keep)
        return out

    def vector_names(self) -> list[str] | None:
        """A name per parameter for tables and CSV columns (None when there are too many to list)."""
        return None

    # ---- records ----------------------------------------------------------------------------------------------------
    def settings(self) -> dict[str, Any]:
        """The family's settings besides its parameter values (what, with the values, fixes the phase)."""
        return {}

    def parameter_values(self) -> dict[str, Any]:
        """The parameter values by name, JSON-ready."""
        return {name: p.detach().cpu().tolist() for name, p in self.named_parameters()}

    def record(self) -> dict[str, Any]:
        """What ``mask.init=PATH`` reads back: kind, settings, levels and values."""
        return {"kind": self.kind, **self.settings(), "levels": self.levels, **self.parameter_values()}

    def summary(self) -> dict[str, float]:
        """Flat, JSON-ready parameter values for metrics and logging (empty when there are too many)."""
        return {}

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], grid: PupilGrid, aperture_diameter_m: float,
                    record: dict | None = None, start_phase: torch.Tensor | None = None,
                    prefix: str = "mask") -> "Mask":  # pragma: no cover - abstract
        """Build from a validated ``mask`` mapping; ``record``: a loaded mask.init record of this family (its values
        win); ``start_phase``: the (n, n) phase of another family's record, fitted (families that fit phases)."""
        raise NotImplementedError

    @classmethod
    def check_record(cls, record: Mapping[str, Any], prefix: str) -> None:
        """Every parameter value and setting of a record of this family by the rules of the config keys (the record's
        key names after ``prefix.``; load_record has checked their JSON types). Default: nothing more to check."""

    @classmethod
    def from_record(cls, cfg: Mapping[str, Any], record: dict, grid: PupilGrid, aperture_diameter_m: float,
                    prefix: str = "mask") -> "Mask":
        """The design a record of this family holds (mask.init), with ``cfg``'s other settings."""
        return cls.from_config(cfg, grid, aperture_diameter_m, record=record, prefix=prefix)

    # ---- other grids --------------------------------------------------------------------------------------------
    def on_grid(self, grid: PupilGrid, aperture_diameter_m: float) -> "Mask":
        """The same physical mask sampled on another pupil grid (a finer one, to check that the design grid resolves
        the phase), frozen."""
        raise NotImplementedError(f"{type(self).__name__}.on_grid")  # pragma: no cover - every family has one


def check_family_keys(cls: type[Mask], settings: Mapping[str, Any], prefix: str) -> None:
    """ConfigError for a key the family does not have, with a hint when it belongs to another family."""
    allowed = {f.name for f in fields(cls.Spec)} - {"prefix"}
    extra = sorted(set(settings) - allowed)
    if extra:
        others = [k for k, c in FAMILIES.items() if c is not cls and extra[0] in {f.name for f in fields(c.Spec)}]
        hint = f" (it is a key of mask={others[0]}: choose the family with the config group, mask={others[0]}, " \
               f"not {prefix}.kind=...)" if others and "kind" in settings else ""
        raise ConfigError(f"{prefix}.{extra[0]}", settings[extra[0]],
                          f"unknown key for a {cls.kind} mask; allowed: {', '.join(sorted(allowed))}{hint}")
