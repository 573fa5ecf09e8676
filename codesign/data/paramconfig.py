"""The validated ``data.params`` block: ranges of the Sec. 6.2 training distribution (SI units, electrons)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping

from codesign.errors import ConfigError, require_choice, require_number

__all__ = ["ParamConfig"]

PREFIX = "data.params"


@dataclass(frozen=True)
class ParamConfig:
    """Ranges and moments of the sampled scene parameters; defaults are the paper's (Sec. 6.2).

    Ranges are closed [lo, hi]; uniform draws unless noted. See sample_scene_params for the distributions.
    """

    alpha_l_range: tuple[float, float] = (0.0, 2.0e6)      # laser strength, uncoded peak / I_sat
    alpha_l_levels: int = 10_000                           # number of predetermined values, both ends among them
    alpha_l_spacing: str = "linear"                        # linear (the paper's), log or mixed: sample_scene_params
    angle_three_sigma_fraction: float = 0.36               # 3 sigma of the incidence = this * [W_s/f, H_s/f] rad
    dark_current_mean_e: float = 0.002                     # mu_c, e-; the sampled value is normal around it
    dark_current_std_fraction: float = 0.5                 # std of the dark current = this * mu_c
    read_noise_mean_range_e: tuple[float, float] = (350.0, 400.0)   # mu_r, e-
    read_noise_std_range_e: tuple[float, float] = (10.0, 11.0)      # sigma_r, e-
    c1_range: tuple[float, float] = (0.0, 0.25)            # relative std of signal-proportional photon noise
    c2_range: tuple[float, float] = (0.9, 1.1)             # photon-noise std modulation
    alpha_b_range: tuple[float, float] = (0.3, 0.7)        # background strength
    exposure_mean_s: float = 0.1                           # t, s (normal)
    exposure_std_s: float = 0.01                           # s; the paper: 0.1 x the mean
    exposure_min_s: float = 1.0e-4                         # s; draws are clipped up to this

    @classmethod
    def from_config(cls, cfg: ParamConfig | Mapping | None) -> ParamConfig:
        """Validate a ``data.params`` mapping (missing keys take the defaults) into a ParamConfig.

        Accepts the params block itself, the whole ``data`` block (its ``params`` entry is used), a ParamConfig
        (returned as is) or None (all defaults). Errors name the key, e.g. ``data.params.c1_range``.
        """
        if cfg is None:
            return cls()
        if isinstance(cfg, ParamConfig):
            return cfg
        if not isinstance(cfg, Mapping) and not hasattr(cfg, "keys"):
            raise ConfigError(PREFIX, cfg, "must be a mapping of parameter ranges")
        if "params" in cfg and "alpha_l_range" not in cfg:
            cfg = cfg["params"]
            if cfg is None:
                return cls()
        unknown = sorted(set(cfg.keys()) - set(_FIELDS))
        if unknown:
            raise ConfigError(f"{PREFIX}.{unknown[0]}", cfg[unknown[0]],
                              f"unknown key; allowed: {', '.join(_FIELDS)}")
        out: dict[str, Any] = {}
        for name in cfg.keys():
            key, v = f"{PREFIX}.{name}", cfg[name]
            if name in _RANGES:
                out[name] = _range(key, v, ALPHA_L_MAX if name == "alpha_l_range" else None)
            elif name == "alpha_l_spacing":
                out[name] = require_choice(key, v, SPACINGS)
            elif name == "alpha_l_levels":
                out[name] = require_number(key, v, lo=1, integer=True)
            elif name in ("exposure_mean_s", "exposure_min_s"):  # a zero exposure would make the sensor blind
                out[name] = require_number(key, v, lo=0.0, lo_open=True)
            else:  # non-negative scalars: fractions, means, stds, the exposure floor
                out[name] = require_number(key, v, lo=0.0)
        pc = cls(**out)
        lo, hi = pc.alpha_l_range
        if pc.alpha_l_spacing != "linear" and lo == 0 < hi < 1:
            raise ConfigError(f"{PREFIX}.alpha_l_range", list(pc.alpha_l_range),
                              f"with alpha_l_spacing={pc.alpha_l_spacing} and a lower end of 0 the upper end must be "
                              ">= 1 (the log levels start at 1, the laser at the saturation level, with 0 as one more "
                              "level)")
        # one level cannot be both ends (the range would be ignored); mixed splits its levels between two such grids
        least = 4 if pc.alpha_l_spacing == "mixed" else 2
        if pc.alpha_l_levels < least and lo < hi:
            raise ConfigError(f"{PREFIX}.alpha_l_levels", pc.alpha_l_levels,
                              f"cannot span {PREFIX}.alpha_l_range = [{lo:g}, {hi:g}]: must be >= {least} (both "
                              f"ends are levels{' of each half' if least == 4 else ''}), or give a range of one "
                              "strength [a, a]")
        return pc


_RANGES = ("alpha_l_range", "read_noise_mean_range_e", "read_noise_std_range_e", "c1_range", "c2_range",
           "alpha_b_range")
_FIELDS = tuple(f.name for f in dataclasses.fields(ParamConfig))
SPACINGS = ("linear", "log", "mixed")


# The largest laser strength, as simulate.laser_strengths': beyond it the float32 simulation overflows (1e40 is inf).
ALPHA_L_MAX = 1e12


def _range(key: str, value: Any, top: float | None = None) -> tuple[float, float]:
    allowed = "must be a pair [lo, hi] of finite numbers with 0 <= lo <= hi" + (f" <= {top:g}" if top else "")
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 2:
        raise ConfigError(key, value, allowed)
    lo, hi = (require_number(key, v, lo=0.0, hi=top) for v in value)
    if lo > hi:
        raise ConfigError(key, list(value), allowed)
    return lo, hi
