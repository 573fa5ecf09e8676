"""Validated settings of ``+experiment=mask_search`` (the ``search.*`` block, see conf/experiment/mask_search.yaml)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from codesign.design.search import CONSTRAINED, LOCAL, check_algorithm
from codesign.errors import ConfigError, require_choice, require_number
from codesign.spec_base import SpecMixin

INITS = ("published", "random", "mask")


def _pair(key: str, value, lo: float | None, hi: float | None, what: str) -> tuple[float, float]:
    """[low, high] with low < high, both finite numbers within [lo, hi]."""
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise ConfigError(key, value, f"must be [low, high] ({what})")
    a, b = (require_number(f"{key}[{i}]", v, lo=lo, hi=hi) for i, v in enumerate(value))
    if a >= b:
        raise ConfigError(key, list(value), f"must be [low, high] with low < high ({what})")
    return a, b


@dataclass(frozen=True)
class SearchSpec(SpecMixin):
    """algorithm: nlopt algorithm with inequality constraints (CONSTRAINED); local_algorithm: polish after a
    global (GN_*) one, from LOCAL or None; polish_max_evals: evaluations of that polish.
    init: start 0 = "published" (the published r_n, theta_n), "random", or "mask" (the configured mask, e.g.
    mask.init=PATH); starts: number of starts, the others random within the bounds from ``seed``.
    max_evals: evaluations per start; xtol_rel, ftol_rel: nlopt's relative stopping tolerances (0 = off).
    lsr_p: p of the smooth LSR; mtf_band: (low, high] normalized frequency of mtf_mean.
    mtf_floor: "published" (the published mask's mtf_mean) or a number; the constraint is
    mtf_mean >= mtf_floor * mtf_floor_factor. energy_floor: "published" (the published mask's PSF energy inside the
    optics window), a fraction in (0, 1], or None: the second constraint, energy in the window >= energy_floor.
    r_bounds: box of r_n (units of lambda f / W_a); theta_bounds: box of theta_n [rad].
    pareto_factors: floor factors of the Pareto sweep (None or empty = off); pareto_starts / pareto_max_evals:
    its starts per factor and evaluations per start. precision: float32 | float64. log_every: evaluations between
    progress lines. ``from_config`` (SpecMixin) rejects unknown keys, naming them.
    """

    algorithm: str = "LN_COBYLA"
    local_algorithm: str | None = "LD_MMA"
    polish_max_evals: int = 50
    init: str = "published"
    starts: int = 4
    seed: int = 0
    max_evals: int = 150
    xtol_rel: float = 1e-4
    ftol_rel: float = 1e-6
    lsr_p: float = 16.0
    mtf_band: tuple = (0.0, 0.5)
    mtf_floor: str | float = "published"
    mtf_floor_factor: float = 1.0
    energy_floor: str | float | None = "published"
    r_bounds: tuple = (0.5, 100.0)
    theta_bounds: tuple = (0.0, 2 * math.pi)
    pareto_factors: tuple | None = (0.7, 0.85, 1.0, 1.15)
    pareto_starts: int = 2
    pareto_max_evals: int = 60
    precision: str = "float32"
    log_every: int = 20
    prefix: str = field(default="search", compare=False, repr=False)

    def __post_init__(self) -> None:
        p, put = self.prefix, lambda k, v: object.__setattr__(self, k, v)
        check_algorithm(f"{p}.algorithm", self.algorithm, CONSTRAINED)
        if self.local_algorithm is not None:
            check_algorithm(f"{p}.local_algorithm", self.local_algorithm, LOCAL)
        for key, lo in (("polish_max_evals", 0), ("starts", 1), ("seed", 0), ("max_evals", 1), ("pareto_starts", 1),
                        ("pareto_max_evals", 1), ("log_every", 1)):
            put(key, require_number(f"{p}.{key}", getattr(self, key), lo=lo, hi=10**9, integer=True))
        require_choice(f"{p}.init", self.init, INITS)
        for key in ("xtol_rel", "ftol_rel"):
            put(key, require_number(f"{p}.{key}", getattr(self, key), lo=0, hi=1, hi_open=True))
        put("lsr_p", require_number(f"{p}.lsr_p", self.lsr_p, lo=1, hi=1024))
        band = _pair(f"{p}.mtf_band", self.mtf_band, 0, 1, "normalized frequency, 0 <= low < high <= 1: beyond the "
                     "incoherent cutoff 1 the MTF is 0")
        put("mtf_band", band)
        if self.mtf_floor != "published":
            v = self.mtf_floor
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v <= 1:  # NaN fails too
                raise ConfigError(f"{p}.mtf_floor", v, "must be published (the published mask's mtf_mean) or a "
                                  "number in (0, 1] (an MTF band mean)")
            put("mtf_floor", float(v))
        if self.energy_floor is not None and self.energy_floor != "published":
            v = self.energy_floor
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v <= 1:  # NaN fails too
                raise ConfigError(f"{p}.energy_floor", v, "must be published (the published mask's PSF energy in "
                                  "the optics window), a fraction in (0, 1], or null (no floor)")
            put("energy_floor", float(v))
        put("mtf_floor_factor", require_number(f"{p}.mtf_floor_factor", self.mtf_floor_factor, lo=0, lo_open=True))
        # HalfRingMask accepts 0 < r <= 1e4; theta is periodic, so any finite box works.
        put("r_bounds", _pair(f"{p}.r_bounds", self.r_bounds, 0, 1e4, "ring radii in lambda f / W_a, 0 < low"))
        if self.r_bounds[0] <= 0:
            raise ConfigError(f"{p}.r_bounds", list(self.r_bounds), "must be [low, high] with 0 < low < high <= 1e4")
        put("theta_bounds", _pair(f"{p}.theta_bounds", self.theta_bounds, None, None, "ring angles in rad"))
        factors = self.pareto_factors
        if factors is not None and not isinstance(factors, (list, tuple)):
            raise ConfigError(f"{p}.pareto_factors", factors, "must be a list of floor factors > 0, or null / [] "
                              "for no sweep")
        factors = tuple(require_number(f"{p}.pareto_factors[{i}]", v, lo=0, lo_open=True)
                        for i, v in enumerate(factors or ()))
        put("pareto_factors", factors or None)
        require_choice(f"{p}.precision", self.precision, ("float32", "float64"))

    def energy_floor_value(self, published_energy: float) -> float | None:
        """The floor on the PSF energy inside the optics window (None = no floor)."""
        return published_energy if self.energy_floor == "published" else self.energy_floor

    def floor_value(self, published_mtf_mean: float, factor: float | None = None) -> float:
        """The MTF floor (band mean) for ``factor`` (default: mtf_floor_factor)."""
        base = published_mtf_mean if self.mtf_floor == "published" else self.mtf_floor
        return base * (self.mtf_floor_factor if factor is None else factor)
