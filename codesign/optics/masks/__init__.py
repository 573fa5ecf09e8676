"""Phase masks behind one interface (``Mask``) and a builder from the ``mask`` config group."""
from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path
from typing import Any, Mapping

from codesign.errors import ConfigError, require_choice, require_list, require_number, require_numbers
from codesign.optics.masks.base import Mask
from codesign.optics.masks.freeform import PixelPhaseMask, ZernikeMask
from codesign.optics.masks.halfring import PUBLISHED_R, PUBLISHED_THETA, HalfRingMask

KINDS = ("halfring", "freeform")
PRESETS = {"published": (PUBLISHED_R, PUBLISHED_THETA)}
_HALFRING_KEYS = {"kind", "preset", "init", "r", "theta", "m_range", "convention", "harmonic_sign", "strategy",
                  "table_size", "r_bounds"}
_FREEFORM_KEYS = {"kind", "basis", "init", "n_terms", "max_coeff_rad", "init_convention"}
log = logging.getLogger("codesign.masks")


BEST_MASK = "the path of a best_mask.json written by +experiment=mask_search"


def load_best_mask(path: Any, key: str, allowed: str = f"must be {BEST_MASK}") -> dict:
    """The contents of a best_mask.json written by +experiment=mask_search: kind "halfring", r (units of
    lambda f / W_a) and theta [rad] of equal lengths; ConfigError naming ``key`` otherwise, whose message starts
    with ``allowed`` (what ``key`` accepts) and then says what is wrong with the file."""
    if not isinstance(path, (str, os.PathLike)):
        raise ConfigError(key, path, allowed)
    try:
        data = json.loads(Path(path).expanduser().read_text())
    except FileNotFoundError:
        raise ConfigError(key, path, f"{allowed}; no such file") from None
    except (OSError, UnicodeDecodeError, ValueError) as err:  # JSONDecodeError is a ValueError
        raise ConfigError(key, path, f"{allowed}; cannot be read as JSON ({err})") from None
    kind = data.get("kind") if isinstance(data, dict) else None
    if kind != "halfring":
        raise ConfigError(key, path, f"{allowed}; the file holds kind {kind!r}, not 'halfring'")
    r, theta = data.get("r"), data.get("theta")
    number = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)  # noqa: E731
    if not (isinstance(r, list) and isinstance(theta, list) and r and len(r) == len(theta)
            and all(map(number, r + theta))):
        raise ConfigError(key, path, f"{allowed}; its r and theta must be non-empty lists of numbers of equal "
                          f"length (got {r!r} and {theta!r})")
    if not all(math.isfinite(v) for v in r + theta):  # json reads NaN / Infinity: name the file, not mask.r[i]
        raise ConfigError(key, path, f"{allowed}; its r and theta hold NaN or Infinity (got {r!r} and {theta!r})")
    return data


def halfring_record(mask: HalfRingMask) -> dict:
    """What load_best_mask reads back: kind, r, theta, and the settings that fix the phase besides them
    (convention, harmonic_sign, m_range), so that mask.init=PATH rebuilds the same mask, freeform included."""
    return {"kind": "halfring", "r": [float(v) for v in mask.r.detach().cpu()],
            "theta": [float(v) for v in mask.theta.detach().cpu()], "convention": mask.convention,
            "harmonic_sign": mask.harmonic_sign,
            "m_range": [(int(mask.orders[0]) - 1) // 2, (int(mask.orders[-1]) - 1) // 2]}


def published_halfring(grid, aperture_diameter_m: float, **kw: Any) -> HalfRingMask:
    """The published five half-ring mask (Sec. 3.1), frozen: the fixed baseline of every experiment."""
    return HalfRingMask(grid, aperture_diameter_m, PUBLISHED_R, PUBLISHED_THETA, **kw).freeze()


def _check_keys(cfg: Mapping[str, Any], allowed: set[str], prefix: str) -> None:
    extra = sorted(set(cfg) - allowed)
    if extra:
        hint = ""
        if cfg.get("kind") == "freeform" and set(extra) & _HALFRING_KEYS:
            hint = f" (to switch masks use the config group, mask=freeform, not {prefix}.kind=freeform)"
        raise ConfigError(f"{prefix}.{extra[0]}", cfg[extra[0]],
                          f"unknown key for a {cfg.get('kind')} mask; allowed: {', '.join(sorted(allowed))}{hint}")


def build_mask(cfg: Mapping[str, Any], grid, aperture_diameter_m: float, prefix: str = "mask") -> Mask:
    """Build a mask from a config mapping (see conf/mask/*.yaml); every value is validated first."""
    kind = require_choice(f"{prefix}.kind", cfg.get("kind"), KINDS)
    if kind == "halfring":
        _check_keys(cfg, _HALFRING_KEYS, prefix)
        preset = cfg.get("preset")
        r, theta = cfg.get("r"), cfg.get("theta")
        init = cfg.get("init")
        if init is not None:  # a searched mask; wins over preset, which has a default that would clash otherwise
            if r is not None or theta is not None:
                raise ConfigError(f"{prefix}.init", init, f"cannot be combined with explicit {prefix}.r / "
                                  f"{prefix}.theta; set {prefix}.init=null to use your own values")
            data = load_best_mask(init, f"{prefix}.init", f"must be null or {BEST_MASK}")
            r, theta = data["r"], data["theta"]
            as_list = lambda v: list(v) if isinstance(v, (list, tuple)) else v  # noqa: E731 - m_range: list/tuple
            for k in ("convention", "harmonic_sign", "m_range"):  # r, theta alone do not fix the phase: say so
                if k in data and k in cfg and as_list(data[k]) != as_list(cfg[k]):
                    log.warning("%s.init: %s was searched with %s=%s, this mask uses %s", prefix, init, k, data[k],
                                cfg[k])
        elif preset is not None:
            require_choice(f"{prefix}.preset", preset, tuple(PRESETS))
            if r is not None or theta is not None:
                raise ConfigError(f"{prefix}.preset", preset,
                                  f"cannot be combined with explicit {prefix}.r / {prefix}.theta; "
                                  f"set {prefix}.preset=null to use your own values")
            r, theta = PRESETS[preset]
        elif r is None or theta is None:
            raise ConfigError(f"{prefix}.r", r, f"{prefix}.r and {prefix}.theta are required when {prefix}.preset "
                              f"is null (allowed presets: {', '.join(PRESETS)})")
        r = require_numbers(f"{prefix}.r", r, "must be a list of ring radii (units of lambda f / W_a)")
        theta = require_numbers(f"{prefix}.theta", theta, f"must be a list of ring angles [rad], as many as {prefix}.r")
        m_range = require_list(f"{prefix}.m_range", cfg.get("m_range", (1, 17)), "must be [m_min, m_max]")
        r_bounds = require_list(f"{prefix}.r_bounds", cfg.get("r_bounds", (0.5, 200.0)), "must be [lo, hi] with "
                                "0 < lo < hi")  # its length and values: HalfRingMask
        return HalfRingMask(grid, aperture_diameter_m, r, theta,
                            m_range=tuple(m_range),
                            convention=cfg.get("convention", "atan2"),
                            harmonic_sign=cfg.get("harmonic_sign", "printed"),
                            strategy=cfg.get("strategy", "exact"),
                            table_size=cfg.get("table_size", 4096), r_bounds=tuple(r_bounds),
                            prefix=prefix)
    _check_keys(cfg, _FREEFORM_KEYS, prefix)
    basis = require_choice(f"{prefix}.basis", cfg.get("basis", "pixel"), ("pixel", "zernike"))
    # checked for either basis (pixel ignores them): a bad value is a typo whichever basis runs
    require_number(f"{prefix}.n_terms", cfg.get("n_terms", 36), lo=1, hi=1000, integer=True)
    require_number(f"{prefix}.max_coeff_rad", cfg.get("max_coeff_rad", 50.0), lo=0, lo_open=True)
    require_choice(f"{prefix}.init_convention", cfg.get("init_convention", "atan2"), ("atan", "atan2"))
    init = cfg.get("init", "published")
    phase = None
    if init == "published":
        conv = cfg.get("init_convention", "atan2")
        phase = published_halfring(grid, aperture_diameter_m, convention=conv).phase().detach()
    elif init != "zero":  # the phase of a searched half ring, with the settings it was searched with
        data = load_best_mask(init, f"{prefix}.init", f"must be one of published, zero or {BEST_MASK}")
        phase = HalfRingMask(grid, aperture_diameter_m, data["r"], data["theta"],
                             m_range=tuple(data.get("m_range", (1, 17))),
                             convention=data.get("convention", cfg.get("init_convention", "atan2")),
                             harmonic_sign=data.get("harmonic_sign", "printed"), prefix=f"{prefix}.init").freeze()
        phase = phase.phase().detach()
    if basis == "pixel":
        return PixelPhaseMask(grid, phase)
    mask = ZernikeMask(grid, aperture_diameter_m, n_terms=cfg.get("n_terms", 36),
                       max_coeff_rad=cfg.get("max_coeff_rad", 50.0), prefix=prefix)
    if phase is not None:
        mask.fit(phase)
    return mask


__all__ = ["Mask", "HalfRingMask", "PixelPhaseMask", "ZernikeMask", "build_mask", "published_halfring",
           "load_best_mask", "halfring_record", "PUBLISHED_R", "PUBLISHED_THETA"]
