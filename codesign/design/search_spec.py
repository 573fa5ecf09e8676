"""Validated settings of ``+experiment=mask_search`` (the ``search.*`` block; its defaults are the config's)."""
from __future__ import annotations

from dataclasses import dataclass, field

from codesign.config.store import register, spec_node
from codesign.design.optimize import ALGORITHMS, LOCAL, check_algorithm, check_size
from codesign.errors import ConfigError, require_choice, require_list, require_number
from codesign.spec_base import SpecMixin

INITS = ("auto", "published", "mask", "defocus", "random")
OBJECTIVES = ("lsr", "restorability")
LSR_OVER = ("design", "wavelengths")
SMALL = 20  # parameter vectors up to this size: several short starts by default
# up to this size LN_COBYLA by default: on the 36 Zernike terms it reached LSR 1.82e-3 in 2400 evaluations (61 s)
# where AL_LBFGS stopped at 2.63e-3 (LD_LBFGS line-search failures at large p; docs/codesign.md Sec. 5)
DERIVATIVE_FREE = 64
DEFAULT_SCHEDULE = (16.0, 32.0, 64.0, 128.0, 256.0, 1024.0)


def _fraction_or(key: str, value, names: tuple[str, ...], what: str):
    """One of ``names``, null, or a number in (0, 1]."""
    if value is None or value in names:
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= 1:  # NaN fails too
        raise ConfigError(key, value, f"must be {', '.join(names)}, {what}, or null (off)")
    return float(value)


@dataclass(frozen=True)
class SearchSpec(SpecMixin):
    """algorithm: auto (LN_COBYLA for masks of <= 64 parameters, AL_LBFGS above), AL_LBFGS (augmented Lagrangian on
    nlopt's LD_LBFGS, docs/codesign.md) or an nlopt algorithm that takes inequality constraints: LD_MMA, LD_CCSAQ,
    LD_SLSQP, LN_COBYLA, GN_ISRES, GN_AGS, GN_ORIG_DIRECT(_L) (global ones are followed by ``local_algorithm`` for
    ``polish_max_evals``). init: start 0 = auto (the family's: published for half rings, mask for spirals, defocus
    for the pixel, spline and Zernike families), published (the published mask in this family: its r_n, theta_n;
    its phase for the pixel, spline and Zernike families), mask (the configured mask, e.g. mask.init=PATH), defocus
    (a defocus of ``defocus_rad``, rad at the aperture's edge: a near flat-top PSF; null: the mask's own
    mask.defocus_rad) or random; starts:
    number of starts (null: 4 for <= 20 parameters, else 1), the others random (the family's random start) from
    ``seed``; max_evals: evaluations per start (null: 150 for <= 20 parameters, else 2400); xtol_rel, ftol_rel:
    nlopt's relative stopping tolerances (0 = off).
    objective: lsr (minimize the smooth LSR) | restorability (maximize the expected Wiener PSNR).
    Constraints: mtf_floor: published (the published mask's mtf_mean on this window), a number in (0, 1], or null,
    times mtf_floor_factor; energy_floor: the PSF energy kept in the optics window, auto (the family's: the
    published mask's for half rings, whose light the window never holds, 0.98 for the others), published, a
    fraction in (0, 1] or null; restorability_floor: expected Wiener PSNR floor [dB] or null; lsr_ceiling: ceiling on
    the smooth LSR (>= the peak: the design's sampled peak stays below it), published (the published mask's sampled
    peak LSR), a number, or null; restorability_alpha_l: the laser strength whose saturated
    footprint the restorability counts (null: none); max_phase_step: cap [rad] on the phase step between
    neighbouring pupil samples, auto (the family's: 1.0 for the pixel and spline families, none for the others),
    a number or null.
    lsr_p_schedule: the continuation on p (auto: 16 .. 1024 for gradient algorithms, [metrics.lsr_p] for
    derivative-free ones) or a list. pareto_factors: floor factors of the Pareto sweep (null or [] = off);
    pareto_starts / pareto_max_evals (null: max_evals / 2): per factor. check: re-check the best design on a pupil
    grid finer by the family's factor and a window that holds its PSF, within metrics.recheck_tolerance.
    lsr_over: design (the LSR at the design wavelength) | wavelengths (the worst LSR over optics.laser_wavelengths_m,
    the surface made as optics.wrap_waves says in material.*: the objective or ceiling takes every line's samples).
    precision: float32 | float64.
    log_every: evaluations between progress lines.
    """

    algorithm: str = "auto"
    local_algorithm: str | None = "LD_MMA"
    polish_max_evals: int = 50
    init: str = "auto"
    defocus_rad: float | None = None
    starts: int | None = None
    seed: int = 0
    max_evals: int | None = None
    xtol_rel: float = 1e-4
    ftol_rel: float = 1e-6
    objective: str = "lsr"
    mtf_floor: str | float | None = "published"
    mtf_floor_factor: float = 1.0
    energy_floor: str | float | None = "auto"
    restorability_floor: float | None = None
    lsr_ceiling: str | float | None = None
    restorability_alpha_l: float | None = None
    max_phase_step: str | float | None = "auto"
    lsr_p_schedule: str | tuple = "auto"
    pareto_factors: tuple | None = (0.7, 0.85, 1.0, 1.15)
    pareto_starts: int = 2
    pareto_max_evals: int | None = 60
    check: bool = True
    lsr_over: str = "design"
    precision: str = "float32"
    log_every: int = 20
    prefix: str = field(default="search", compare=False, repr=False)

    def __post_init__(self) -> None:
        p, put = self.prefix, lambda k, v: object.__setattr__(self, k, v)
        if self.algorithm != "auto":
            check_algorithm(f"{p}.algorithm", self.algorithm, ALGORITHMS)
        if self.local_algorithm is not None:
            check_algorithm(f"{p}.local_algorithm", self.local_algorithm, LOCAL)
        for key, lo in (("polish_max_evals", 0), ("seed", 0), ("pareto_starts", 1), ("log_every", 1)):
            put(key, require_number(f"{p}.{key}", getattr(self, key), lo=lo, hi=10**9, integer=True))
        for key in ("starts", "max_evals", "pareto_max_evals"):
            if getattr(self, key) is not None:
                put(key, require_number(f"{p}.{key}", getattr(self, key), lo=1, hi=10**9, integer=True))
        require_choice(f"{p}.init", self.init, INITS)
        if self.defocus_rad is not None:
            put("defocus_rad", require_number(f"{p}.defocus_rad", self.defocus_rad, lo=0, hi=1e4))
        require_choice(f"{p}.objective", self.objective, OBJECTIVES)
        for key in ("xtol_rel", "ftol_rel"):
            put(key, require_number(f"{p}.{key}", getattr(self, key), lo=0, hi=1, hi_open=True))
        put("mtf_floor", _fraction_or(f"{p}.mtf_floor", self.mtf_floor, ("published",),
                                      "a number in (0, 1] (an MTF band mean)"))
        put("energy_floor", _fraction_or(f"{p}.energy_floor", self.energy_floor, ("auto", "published"),
                                         "a fraction in (0, 1]"))
        put("mtf_floor_factor", require_number(f"{p}.mtf_floor_factor", self.mtf_floor_factor, lo=0, lo_open=True))
        if self.restorability_floor is not None:
            put("restorability_floor", require_number(f"{p}.restorability_floor", self.restorability_floor,
                                                      lo=0, hi=200))
        if self.lsr_ceiling not in (None, "published"):
            put("lsr_ceiling", require_number(f"{p}.lsr_ceiling", self.lsr_ceiling, lo=0, lo_open=True, hi=1))
        if self.restorability_alpha_l is not None:
            put("restorability_alpha_l", require_number(f"{p}.restorability_alpha_l", self.restorability_alpha_l,
                                                        lo=0, hi=1e12))
        if self.max_phase_step not in (None, "auto"):
            put("max_phase_step", require_number(f"{p}.max_phase_step", self.max_phase_step, lo=0, lo_open=True,
                                                 hi=3.2))
        if self.objective == "restorability" and self.lsr_ceiling is None:
            raise ConfigError(f"{p}.lsr_ceiling", None, "must be set (published or a number) with "
                              "search.objective=restorability: maximizing restorability alone removes the mask")
        if self.objective == "lsr" and self.mtf_floor is None and self.restorability_floor is None:
            raise ConfigError(f"{p}.mtf_floor", None, "a search for the lowest LSR needs a floor on what the mask "
                              "keeps: set search.mtf_floor or search.restorability_floor")
        if self.lsr_p_schedule != "auto":
            allowed = "must be auto or a list of smooth-LSR exponents p >= 1 (the continuation)"
            sched = require_list(f"{p}.lsr_p_schedule", self.lsr_p_schedule, allowed)
            if not sched:
                raise ConfigError(f"{p}.lsr_p_schedule", self.lsr_p_schedule, allowed)
            put("lsr_p_schedule", tuple(require_number(f"{p}.lsr_p_schedule[{i}]", v, lo=1, hi=65536)
                                        for i, v in enumerate(sched)))
        factors = self.pareto_factors
        if factors is not None and not isinstance(factors, (list, tuple)):
            raise ConfigError(f"{p}.pareto_factors", factors, "must be a list of floor factors > 0, or null / [] "
                              "for no sweep")
        factors = tuple(require_number(f"{p}.pareto_factors[{i}]", v, lo=0, lo_open=True)
                        for i, v in enumerate(factors or ()))
        put("pareto_factors", factors or None)
        if not isinstance(self.check, bool):
            raise ConfigError(f"{p}.check", self.check, "must be true or false")
        require_choice(f"{p}.precision", self.precision, ("float32", "float64"))
        require_choice(f"{p}.lsr_over", self.lsr_over, LSR_OVER)

    # ---- what "auto" means for a mask of ``n`` parameters ---------------------------------------------------------
    def resolved_algorithm(self, n: int) -> str:
        """The nlopt algorithm for ``n`` parameters: the configured one, or with auto LN_COBYLA up to DERIVATIVE_FREE
        parameters and AL_LBFGS beyond."""
        return self.algorithm if self.algorithm != "auto" else ("LN_COBYLA" if n <= DERIVATIVE_FREE else "AL_LBFGS")

    def check_size(self, n: int, family: str) -> None:
        """The algorithm (and a global one's polish, local_algorithm) able to run a ``family`` mask of ``n``
        parameters (optimize.SIZE_LIMITS); ConfigError naming the key and the algorithms that can, before the
        search (GN_ISRES on a spline mask crashed the process without a word, GN_AGS and LD_SLSQP failed in it)."""
        algorithm = self.resolved_algorithm(n)
        check_size(f"{self.prefix}.algorithm", algorithm, n, family, ALGORITHMS)
        if algorithm.startswith("G") and self.local_algorithm is not None and self.polish_max_evals > 0:
            check_size(f"{self.prefix}.local_algorithm", self.local_algorithm, n, family, LOCAL)

    def resolved_starts(self, n: int) -> int:
        """The number of starts for ``n`` parameters: the configured one, or 4 for small vectors and 1 for large
        ones."""
        return self.starts if self.starts is not None else (4 if n <= SMALL else 1)

    def resolved_max_evals(self, n: int) -> int:
        """The evaluations per start for ``n`` parameters: the configured number, or 150 for small vectors and 2400
        for large ones."""
        return self.max_evals if self.max_evals is not None else (150 if n <= SMALL else 2400)

    def schedule(self, n: int, lsr_p: float) -> tuple[float, ...]:
        """The smooth LSR's p at each stage of a start: the configured schedule, or with auto DEFAULT_SCHEDULE for
        gradient algorithms and ``lsr_p`` alone otherwise."""
        if self.lsr_p_schedule != "auto":
            return tuple(self.lsr_p_schedule)
        return DEFAULT_SCHEDULE if self.resolved_algorithm(n).startswith(("LD", "GD", "AL")) else (lsr_p,)


register("search", "default", spec_node(SearchSpec, seed="${seed}"))
