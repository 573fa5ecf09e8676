"""Mask records: the JSON that ``mask.init=PATH`` reads back, and its writer (mask_search, joint and psf).

A record holds ``kind``, the family's settings and parameter values (``Mask.record()``), and usually the optics the
mask was designed for (``optics``: OpticsSpec fields) and its figures of merit. Records written before families
existed (best_mask.json / learned_mask.json with kind halfring, r, theta and optionally convention, harmonic_sign,
m_range) are records of the same form.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import fields
from pathlib import Path
from typing import Any

from codesign.errors import ConfigError
from codesign.io import files as io

RECORD_PATH = ("the path of a mask record (best_mask.json of +experiment=mask_search, learned_mask.json of joint, "
               "mask.json of psf)")
# the figures of merit the writers add (write_record refuses any other): with the family's Spec keys, record_values
# and record_settings (declared on its class), all a record may hold
FIGURE_KEYS = ("lsr", "lsr_smooth", "lsr_sampled", "mtf_mean", "window_energy", "lsr_limit", "lsr_over_limit",
               "restorability", "feasible", "check_agree", "phase_resolved")


def _families() -> dict:
    from codesign.optics.masks import FAMILIES, families

    families()  # every family registered
    return FAMILIES


def record_keys(kind: str) -> set[str]:
    """Every key a record of family ``kind`` may hold."""
    cls = _families()[kind]
    spec = {f.name for f in fields(cls.Spec)} - {"prefix", "init"}
    return {"kind", "levels", "optics", *cls.record_values, *cls.record_settings, *FIGURE_KEYS} | spec


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def load_record(path: Any, key: str, allowed: str) -> dict:
    """The contents of a mask record at ``path``; ConfigError naming ``key`` otherwise, whose message starts with
    ``allowed`` (what ``key`` accepts) and then says what is wrong with the file."""
    if not isinstance(path, (str, os.PathLike)):
        raise ConfigError(key, path, allowed)
    try:
        data = json.loads(Path(path).expanduser().read_text())
    except FileNotFoundError:
        raise ConfigError(key, path, f"{allowed}; no such file") from None
    except (OSError, UnicodeDecodeError, ValueError) as err:  # JSONDecodeError is a ValueError
        raise ConfigError(key, path, f"{allowed}; cannot be read as JSON ({err})") from None
    kind = data.get("kind") if isinstance(data, dict) else None
    families = _families()
    if kind not in families:
        raise ConfigError(key, path, f"{allowed}; the file holds kind {kind!r}, not a mask family "
                          f"({', '.join(sorted(families))})")
    values = families[kind].record_values
    unknown = sorted(set(data) - record_keys(kind))
    if unknown:
        raise ConfigError(key, path, f"{allowed}; its key(s) {', '.join(unknown)} are not keys of a {kind} record "
                          f"(allowed: {', '.join(sorted(record_keys(kind)))})")
    bad = [name for name, what in values.items()
           if not (what == "number" and _number(data.get(name))
                   or what == "list" and isinstance(data.get(name), list) and data[name]
                   and all(map(_number, data[name])))]
    if kind == "halfring":
        r, theta = data.get("r"), data.get("theta")
        if bad or len(r) != len(theta):
            raise ConfigError(key, path, f"{allowed}; its r and theta must be non-empty lists of numbers of equal "
                              f"length (got {r!r} and {theta!r})")
    elif bad:
        raise ConfigError(key, path, f"{allowed}; a {kind} record needs {', '.join(values)} "
                          f"(missing or not numbers: {', '.join(bad)})")
    numbers = [v for name in values for v in (data[name] if isinstance(data[name], list)
                                                           else [data[name]])]
    if not all(math.isfinite(v) for v in numbers):  # json reads NaN / Infinity: name the file, not mask.r[i]
        what = f"its r and theta hold NaN or Infinity (got {data['r']!r} and {data['theta']!r})" \
            if kind == "halfring" else "its values hold NaN or Infinity"
        raise ConfigError(key, path, f"{allowed}; {what}")
    return data


def optics_record(spec) -> dict:
    """The OpticsSpec's fields (SI units) as a JSON-ready dict."""
    return {f.name: getattr(spec, f.name) for f in fields(spec) if f.name != "prefix"}


def design_record(mask, spec, figures: dict | None = None) -> dict:
    """``mask.record()`` plus ``optics`` (the spec it was evaluated on) and the scalar figures of merit (names from
    FIGURE_KEYS: what mask.init reads back accepts exactly those)."""
    other = sorted(set(figures or {}) - set(FIGURE_KEYS))
    if other:  # a writer's new figure must be registered, or the record it writes would be refused when read
        raise ValueError(f"design_record: figure(s) {', '.join(other)} not in FIGURE_KEYS "
                         f"(codesign/optics/masks/records.py)")
    scalars = {k: v for k, v in (figures or {}).items() if isinstance(v, (int, float, str, bool)) or v is None}
    return {**mask.record(), "optics": optics_record(spec), **scalars}


def write_record(path: Path, mask, spec, figures: dict | None = None) -> dict:
    """Write ``design_record`` atomically to ``path`` (mask_search's best_mask.json, joint's learned_mask.json,
    psf's mask.json); returns it."""
    record = design_record(mask, spec, figures)
    io.write_json(path, record)
    return record
