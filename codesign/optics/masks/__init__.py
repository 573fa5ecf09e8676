"""Phase masks behind one interface (``Mask``) and a builder from the ``mask`` config group."""
from __future__ import annotations

from typing import Any, Mapping

from codesign.errors import ConfigError, require_choice
from codesign.optics.masks.base import Mask
from codesign.optics.masks.freeform import PixelPhaseMask, ZernikeMask
from codesign.optics.masks.halfring import PUBLISHED_R, PUBLISHED_THETA, HalfRingMask

KINDS = ("halfring", "freeform")
PRESETS = {"published": (PUBLISHED_R, PUBLISHED_THETA)}
_HALFRING_KEYS = {"kind", "preset", "r", "theta", "m_range", "convention", "harmonic_sign", "strategy",
                  "table_size", "r_bounds"}
_FREEFORM_KEYS = {"kind", "basis", "init", "n_terms", "max_coeff_rad", "init_convention"}


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
        if preset is not None:
            require_choice(f"{prefix}.preset", preset, tuple(PRESETS))
            if r is not None or theta is not None:
                raise ConfigError(f"{prefix}.preset", preset,
                                  f"cannot be combined with explicit {prefix}.r / {prefix}.theta; "
                                  f"set {prefix}.preset=null to use your own values")
            r, theta = PRESETS[preset]
        elif r is None or theta is None:
            raise ConfigError(f"{prefix}.r", r, f"{prefix}.r and {prefix}.theta are required when {prefix}.preset "
                              f"is null (allowed presets: {', '.join(PRESETS)})")
        return HalfRingMask(grid, aperture_diameter_m, list(r), list(theta),
                            m_range=tuple(cfg.get("m_range", (1, 17))),
                            convention=cfg.get("convention", "atan2"),
                            harmonic_sign=cfg.get("harmonic_sign", "printed"),
                            strategy=cfg.get("strategy", "exact"),
                            table_size=cfg.get("table_size", 4096), r_bounds=tuple(cfg.get("r_bounds", (0.5, 200.0))),
                            prefix=prefix)
    _check_keys(cfg, _FREEFORM_KEYS, prefix)
    basis = require_choice(f"{prefix}.basis", cfg.get("basis", "pixel"), ("pixel", "zernike"))
    init = require_choice(f"{prefix}.init", cfg.get("init", "published"), ("published", "zero"))
    phase = None
    if init == "published":
        conv = cfg.get("init_convention", "atan2")
        phase = published_halfring(grid, aperture_diameter_m, convention=conv).phase().detach()
    if basis == "pixel":
        return PixelPhaseMask(grid, phase)
    mask = ZernikeMask(grid, aperture_diameter_m, n_terms=cfg.get("n_terms", 36),
                       max_coeff_rad=cfg.get("max_coeff_rad", 50.0), prefix=prefix)
    if phase is not None:
        mask.fit(phase)
    return mask


__all__ = ["Mask", "HalfRingMask", "PixelPhaseMask", "ZernikeMask", "build_mask", "published_halfring",
           "PUBLISHED_R", "PUBLISHED_THETA"]
