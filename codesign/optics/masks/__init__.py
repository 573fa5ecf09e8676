"""Phase masks behind one interface (base.Mask), one module per family, and a builder from the ``mask`` config.

Families: halfring (the paper's rings, any number), zernike, pixel (a phase per pupil sample), spline (a smooth
freeform surface: cubic B-spline on a control grid), spiral (vortex axicon). ``mask=freeform``
(mask.basis=pixel|zernike) is kept as the name the pixel and Zernike families had.
"""
from __future__ import annotations

import importlib
import logging
import os
import pkgutil
from typing import Any, Mapping

import torch

from codesign.config.store import register
from codesign.errors import ConfigError, require_choice
from codesign.optics.masks.base import (
    FAMILIES,
    NAMED_STARTS,
    Mask,
    MaskSpec,
    check_family_keys,
    quantize,
)
from codesign.optics.masks.halfring import PUBLISHED_R, PUBLISHED_THETA, HalfRingMask
from codesign.optics.masks.pixel import PixelPhaseMask
from codesign.optics.masks.records import RECORD_PATH, check_mask_init, init_allowed, load_record, write_record
from codesign.optics.masks.spiral import SpiralMask
from codesign.optics.masks.spline import SplineMask
from codesign.optics.masks.zernike import ZernikeMask, ZernikeSpec

log = logging.getLogger("codesign.masks")
# the keys of mask=freeform, translated to the pixel or Zernike family
FREEFORM_KEYS = ("kind", "basis", "init", "n_terms", "max_coeff_rad", "init_convention", "levels", "defocus_rad")
FREEFORM_DEFAULTS = {**{k: v for k, v in ZernikeSpec.defaults().items() if k in FREEFORM_KEYS}, "kind": "freeform",
                     "basis": "pixel"}


def families() -> tuple[str, ...]:
    """Every registered family (importing each module of this package registers it)."""
    for info in pkgutil.iter_modules(__path__):
        importlib.import_module(f"{__name__}.{info.name}")
    return tuple(sorted(FAMILIES))


def _from_freeform(settings: Mapping[str, Any], prefix: str) -> dict:
    """mask=freeform (basis pixel|zernike) as the pixel or Zernike family's settings (the mask block)."""
    extra = sorted(set(settings) - set(FREEFORM_KEYS))
    if extra:
        hint = f" (to switch masks use the config group, e.g. mask=halfring, not {prefix}.kind=...)" \
            if set(extra) & set(HalfRingMask.Spec.defaults()) else ""
        raise ConfigError(f"{prefix}.{extra[0]}", settings[extra[0]], f"unknown key for a freeform mask; allowed: "
                          f"{', '.join(sorted(FREEFORM_KEYS))}{hint}")
    basis = require_choice(f"{prefix}.basis", settings.get("basis", "pixel"), ("pixel", "zernike"))
    keep = ("init", "init_convention", "levels", "defocus_rad") + (("n_terms", "max_coeff_rad") if basis == "zernike"
                                                                     else ())
    # every freeform key is checked for either basis (pixel ignores n_terms and max_coeff_rad): a bad value is a
    # typo whichever basis runs
    keys = [k for k in FREEFORM_KEYS if k in settings and k not in ("kind", "basis")]
    ZernikeMask.Spec.from_config({k: settings[k] for k in keys}, prefix)
    return {"kind": basis, **{k: settings[k] for k in keep if k in settings}}


def check_mask_settings(settings: Mapping[str, Any], prefix: str = "mask") -> dict:
    """The mask ``settings`` checked as ``prefix.*`` keys (family, its keys, each value: levels etc.) without
    building the mask; returns them as the family's own (mask=freeform as pixel or zernike). build_mask's first
    step, and the API's check of a composed config's mask block (it was accepted by psf_and_lsr, mask.levels=1)."""
    settings = dict(settings)
    require_choice(f"{prefix}.kind", settings.get("kind"), families() + ("freeform",))
    if settings.get("kind") == "freeform":
        settings = _from_freeform(settings, prefix)
    kind = settings["kind"]
    cls = FAMILIES[kind]
    check_family_keys(cls, settings, prefix)
    cls.Spec.from_config({k: v for k, v in settings.items() if k != "kind"} | {"kind": kind}, prefix)  # levels etc.
    return settings


def build_mask(cfg: Mapping[str, Any], grid, aperture_diameter_m: float, prefix: str = "mask") -> Mask:
    """Build a mask from a config mapping (``kind`` picks the family; see conf/README of each family's Spec);
    every value is validated first. ``init``: a record path starts the mask from that record (a record of another
    family is taken as a phase, where the family can start from one)."""
    cfg = check_mask_settings(cfg, prefix)
    kind = cfg["kind"]
    cls = FAMILIES[kind]
    init = cfg.get("init")
    named = NAMED_STARTS if cls.fits_phases else ()
    if init is None or init in named:
        return cls.from_config(cfg, grid, aperture_diameter_m, prefix=prefix)
    record = load_record(init, f"{prefix}.init", init_allowed(kind))
    if record["kind"] == kind:
        # the record is the design: the settings that fix its phase with its values are the record's
        as_list = lambda v: list(v) if isinstance(v, (list, tuple)) else v  # noqa: E731
        for k in cls.record_settings:
            if k in record and k in cfg and as_list(record[k]) != as_list(cfg[k]):
                log.warning("%s.init: %s was designed with %s=%s; it keeps it (the configured %s is ignored)",
                            prefix, init, k, record[k], cfg[k])
            if k in record:
                cfg[k] = record[k]
        cfg["levels"] = design_levels(cfg, record, prefix)
        return cls.from_record(cfg, record, grid, aperture_diameter_m, prefix=prefix)
    if not cls.fits_phases:
        raise ConfigError(f"{prefix}.init", init, f"holds a {record['kind']} mask; a {kind} mask starts only from a "
                          f"{kind} record: use mask={record['kind']} to build it as it is")
    target = record_phase(record, grid, aperture_diameter_m)
    mask = cls.from_config(cfg, grid, aperture_diameter_m, start_phase=target, prefix=prefix)
    report_fit(mask, target, record, f"{prefix}.init {init}", prefix)
    return mask


# a fitted record's RMS phase error [rad] above which the mask is said not to be the design: a 25th of a wave (a
# half-ring design fitted by the spline family: 1.14 rad, its LSR 0.0086 -> 0.053; by the pixel family: 0)
FIT_WARNING_RAD = 0.25


@torch.no_grad()
def fit_error_rad(mask: Mask, target: torch.Tensor) -> float:
    """RMS phase error [rad] over the aperture's samples between ``mask``'s continuous phase (before any levels)
    and the (n, n) ``target``, modulo 2 pi and less the mean offset (neither changes the PSF)."""
    grid = mask.grid
    want = target.reshape(-1)[grid.support].to(torch.float64)
    diff = torch.polar(torch.ones_like(want), mask.support_phase().detach().to(torch.float64) - want)
    diff = diff * torch.conj(diff.mean() / diff.mean().abs().clamp_min(1e-30))  # the common offset removed
    return float(torch.angle(diff).pow(2).mean().sqrt())


def report_fit(mask: Mask, target: torch.Tensor, record: Mapping[str, Any], where: str, prefix: str = "mask") -> None:
    """Say how well a record of another family was fitted (its RMS phase error); a warning above FIT_WARNING_RAD:
    the mask then is not the design (its PSF and LSR differ), which was said nowhere."""
    error = fit_error_rad(mask, target)
    spread = float(target.reshape(-1)[mask.grid.support].to(torch.float64).std())
    text = (f"{where}: a {record['kind']} record fitted by the {mask.kind} family: RMS phase error {error:.3g} rad "
            f"over the aperture (the design's phase spreads {spread:.3g} rad RMS)")
    if error > FIT_WARNING_RAD:
        _say(logging.WARNING, f"{text}, above {FIT_WARNING_RAD:g} rad: the mask is not the design (its PSF and LSR "
                              f"differ); build it as designed with {prefix}={record['kind']}")
    else:
        _say(logging.INFO, text)


_SAID: set = set()  # the levels notes already logged (export and tolerance build one design twice)


def _say(level: int, text: str) -> None:
    if text not in _SAID:
        _SAID.add(text)
        log.log(level, "%s", text)


def design_levels(settings: Mapping[str, Any], record: Mapping[str, Any], prefix: str = "mask") -> int | None:
    """The levels a record's design is built with: its own (an 8-level design stays one), unless ``levels`` is set
    in the config (quantizing it anew, said when it differs)."""
    ours, theirs = settings.get("levels"), record.get("levels")
    where = f"{prefix}.init {getattr(record, 'path', '(record)')}"
    if ours is None:
        if theirs is not None:
            _say(logging.INFO, f"{where}: levels = {theirs}: the design is quantized to its {theirs} levels")
        return theirs
    if ours != theirs:
        theirs = "null (continuous)" if theirs is None else theirs
        _say(logging.WARNING, f"{where}: levels = {theirs} (the design's); {prefix}.levels = {ours} is used "
                              f"instead: the design is quantized to {ours} levels")
    return ours


def levels_of_design(settings: Mapping[str, Any], prefix: str = "mask") -> int | None:
    """The levels the design ``settings`` (a mask block) names is built with (``levels``, else its record's): for a
    fabrication export that makes a plate of its levels unless told otherwise."""
    init = settings.get("init")
    if settings.get("levels") is not None or not isinstance(init, (str, os.PathLike)) or init in NAMED_STARTS:
        return settings.get("levels")
    return load_record(init, f"{prefix}.init", f"must be null or {RECORD_PATH}").get("levels")


def config_of_design(settings: Mapping[str, Any], prefix: str = "mask") -> dict:
    """The mask config that builds the design ``settings`` names: with ``init`` a record of another family than the
    configured one (e.g. a spline best_mask.json under the default mask=halfring), that family's defaults and the
    record; otherwise ``settings`` itself. For experiments that take a finished design of any family (export,
    tolerance); the others keep refusing a family mismatch, where it is more likely a mistake."""
    settings = dict(settings)
    init = settings.get("init")
    if not isinstance(init, (str, os.PathLike)) or init in NAMED_STARTS:
        return settings
    record = load_record(init, f"{prefix}.init", f"must be null or {RECORD_PATH}")
    kind = settings.get("basis") if settings.get("kind") == "freeform" else settings.get("kind")
    if record["kind"] == kind:
        return settings
    return {**FAMILIES[record["kind"]].Spec.defaults(), "kind": record["kind"], "init": init,
            "levels": settings.get("levels")}  # a typed mask.levels holds for any family's design (design_levels)


def record_phase(record: dict, grid, aperture_diameter_m: float) -> torch.Tensor:
    """The (n, n) phase of a loaded record's mask on ``grid`` (a pixel record designed on another grid: its plate
    sampled there, cell by cell)."""
    cls = FAMILIES[record["kind"]]
    settings = {k: v for k, v in record.items() if k not in cls.record_values}
    mask = cls.from_record({**settings, "levels": record.get("levels"), "preset": None}, record, grid,
                           aperture_diameter_m)
    return mask.freeze().phase().detach()


def published_mask_config(settings: Mapping[str, Any]) -> dict:
    """The settings of the published five half-ring mask under the conventions of mask ``settings`` (m_range,
    atan/atan2, signs) when that mask is a half ring; under its init_convention for the pixel and Zernike families."""
    base = {**HalfRingMask.Spec.defaults(), "preset": "published"}
    if settings.get("kind") == "halfring":
        keep = ("m_range", "convention", "harmonic_sign", "strategy", "table_size", "r_bounds")
        return {**base, **{k: settings[k] for k in keep if k in settings}}
    return {**base, "convention": settings.get("init_convention", "atan2")}


def published_halfring(grid, aperture_diameter_m: float, **kw: Any) -> HalfRingMask:
    """The published five half-ring mask (Sec. 3.1), frozen: the fixed baseline of every experiment."""
    return HalfRingMask(grid, aperture_diameter_m, PUBLISHED_R, PUBLISHED_THETA, **kw).freeze()


# the config options mask=<family> (every family's Spec defaults) and mask=freeform
for _kind in families():
    register("mask", _kind, FAMILIES[_kind].Spec.defaults(), spec=FAMILIES[_kind].Spec)
register("mask", "freeform", dict(FREEFORM_DEFAULTS), spec=ZernikeSpec)

__all__ = ["Mask", "MaskSpec", "HalfRingMask", "PixelPhaseMask", "ZernikeMask", "SpiralMask", "SplineMask", "FAMILIES",
           "build_mask", "check_mask_init", "check_mask_settings", "config_of_design", "design_levels", "families",
           "levels_of_design",
           "load_record", "published_halfring", "published_mask_config", "quantize", "record_phase", "write_record",
           "PUBLISHED_R", "PUBLISHED_THETA", "RECORD_PATH"]
