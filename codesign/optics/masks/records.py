"""Mask records: the JSON that ``mask.init=PATH`` reads back (written by mask_search, joint and psf).

A record holds ``kind``, the family's settings and parameter values (``Mask.record()``), and usually the optics the
mask was designed for (``optics``: OpticsSpec fields) and its figures of merit. Records written before families
existed (best_mask.json / learned_mask.json with kind halfring, r, theta and optionally convention, harmonic_sign,
m_range) are records of the same form.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

from codesign.errors import ConfigError

RECORD_PATH = ("the path of a mask record (best_mask.json of +experiment=mask_search, learned_mask.json of joint, "
               "mask.json of psf)")
# the parameter values each family's record must hold: name -> "list" (non-empty list of numbers) or "number"
RECORD_VALUES: dict[str, dict[str, str]] = {
    "halfring": {"r": "list", "theta": "list"},
    "pixel": {"values": "list", "grid_n": "number", "pitch_m": "number"},
    "zernike": {"coeffs": "list"},
    "spiral": {"charge": "number", "axicon_cycles": "number", "defocus_rad": "number"},
    "spline": {"controls": "list", "control_pitch_m": "number", "control_half": "number"},
}


# the family settings a record holds besides its values (Mask.settings()), and the figures of merit the writers add
# (codesign/design/records.py refuses to write any other): with the family Spec's keys, all a record may hold
RECORD_SETTINGS: dict[str, tuple[str, ...]] = {
    "halfring": ("convention", "harmonic_sign", "m_range", "r_bounds"),
    "zernike": ("n_terms", "max_coeff_rad"),
    "spiral": ("charge_bounds", "axicon_bounds", "defocus_bounds"),
    "pixel": (),
    "spline": (),
}
FIGURE_KEYS = ("lsr", "lsr_smooth", "lsr_sampled", "mtf_mean", "window_energy", "lsr_limit", "lsr_over_limit",
               "restorability", "feasible", "check_agree", "phase_resolved")


def record_keys(kind: str) -> set[str]:
    """Every key a record of family ``kind`` may hold."""
    from dataclasses import fields

    from codesign.optics.masks.base import FAMILIES  # registered by the package by the time records are read

    spec = {f.name for f in fields(FAMILIES[kind].Spec)} - {"prefix", "init"} if kind in FAMILIES else set()
    return {"kind", "levels", "optics", *RECORD_VALUES[kind], *RECORD_SETTINGS[kind], *FIGURE_KEYS} | spec


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
    if kind not in RECORD_VALUES:
        raise ConfigError(key, path, f"{allowed}; the file holds kind {kind!r}, not a mask family "
                          f"({', '.join(sorted(RECORD_VALUES))})")
    unknown = sorted(set(data) - record_keys(kind))
    if unknown:
        raise ConfigError(key, path, f"{allowed}; its key(s) {', '.join(unknown)} are not keys of a {kind} record "
                          f"(allowed: {', '.join(sorted(record_keys(kind)))})")
    bad = [name for name, what in RECORD_VALUES[kind].items()
           if not (what == "number" and _number(data.get(name))
                   or what == "list" and isinstance(data.get(name), list) and data[name]
                   and all(map(_number, data[name])))]
    if kind == "halfring":
        r, theta = data.get("r"), data.get("theta")
        if bad or len(r) != len(theta):
            raise ConfigError(key, path, f"{allowed}; its r and theta must be non-empty lists of numbers of equal "
                              f"length (got {r!r} and {theta!r})")
    elif bad:
        raise ConfigError(key, path, f"{allowed}; a {kind} record needs {', '.join(RECORD_VALUES[kind])} "
                          f"(missing or not numbers: {', '.join(bad)})")
    numbers = [v for name in RECORD_VALUES[kind] for v in (data[name] if isinstance(data[name], list)
                                                           else [data[name]])]
    if not all(math.isfinite(v) for v in numbers):  # json reads NaN / Infinity: name the file, not mask.r[i]
        what = f"its r and theta hold NaN or Infinity (got {data['r']!r} and {data['theta']!r})" \
            if kind == "halfring" else "its values hold NaN or Infinity"
        raise ConfigError(key, path, f"{allowed}; {what}")
    return data
