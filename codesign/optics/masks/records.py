"""Mask records: the JSON that ``mask.init=PATH`` reads back, and its writer (mask_search, joint and psf).

A record holds ``kind``, the family's settings and parameter values (``Mask.record()``), its ``levels``, usually the
optics the mask was designed for (``optics``: OpticsSpec fields) and its figures of merit. Records written before
families existed (best_mask.json / learned_mask.json with kind halfring, r, theta and optionally convention,
harmonic_sign, m_range) are records of the same form.

A record is read whole: every key is used or refused, each value by the rules of the config key it stands for
(a message names the file and the key: ``mask.init FILE: levels = 1: ...``), the file's size bounded before it is
read, a key given twice refused; ``check_mask_init`` also refuses a record made for other optics than the
configured ones, before any work. A record may be stored gzip-compressed (best_mask.json.gz: a spline or pixel
record's numbers take 2.3x less room); it is read the same way, its unpacked size bounded as well.
"""
from __future__ import annotations

import gzip
import json
import logging
import math
import os
import stat
import zlib
from contextlib import contextmanager
from dataclasses import fields
from io import BytesIO
from pathlib import Path
from typing import Any, Mapping

from codesign.errors import ConfigError, require_number, special_file
from codesign.io import files as io
from codesign.optics.masks.base import NAMED_STARTS, require_levels
from codesign.optics.spec import OpticsSpec

RECORD_PATH = ("the path of a mask record (best_mask.json of +experiment=mask_search, learned_mask.json of joint, "
               "mask.json of psf)")
# the figures of merit the writers add (write_record refuses any other): with kind, levels, optics and the family's
# record_values and record_settings (declared on its class), all a record may hold
FIGURE_KEYS = ("lsr", "lsr_smooth", "lsr_sampled", "mtf_mean", "window_energy", "lsr_limit", "lsr_over_limit",
               "restorability", "feasible", "check_agree", "phase_resolved")
# what the record of a search that did not finish adds (mask_search on SIGINT / SIGTERM writes best_mask.partial.json
# with "partial": true and "stop_reason": why and where it stopped): read back with a warning naming it, never taken
# silently for a finished design
PARTIAL_KEYS = ("partial", "stop_reason")
FLAG_KEYS = ("feasible", "check_agree", "phase_resolved")  # the figures that are true / false (or null)
# the optics that fix what a design's phase does: a record made for other values is refused (its phase, in rad,
# belongs to its wavelength; its rings' radii and the focal window scale with lambda f / W_a)
DESIGN_OPTICS = ("wavelength_m", "focal_length_m", "aperture_diameter_m", "supergaussian_order")
# the largest record read: a pixel record's values take ~12 bytes each, so ~2.8 million phases (a pupil grid of
# ~1900 samples across the aperture, 5x the paper's); bounded before reading, as a stray file may be anything
MAX_RECORD_BYTES = 32 * 2**20
# the first bytes of every gzip file: no JSON text starts with them, so a compressed record is told by what it holds,
# whatever its name
GZIP_MAGIC = b"\x1f\x8b"
_FIELD = "\x00record"  # the prefix of a record's keys while its values are checked (replaced by "mask.init FILE:")


class Record(dict):
    """A loaded record: its contents, and ``path`` (the file, as given) for messages raised later."""

    def __init__(self, data: Mapping[str, Any], path: Any):
        super().__init__(data)
        self.path = path


class _Shown:
    """A value as a message shows it: its repr, cut short (a record's lists hold up to millions of numbers)."""

    def __init__(self, value: Any, limit: int = 80):
        self.value, self.limit = value, limit

    def __repr__(self) -> str:
        try:
            text = repr(self.value)
        except RecursionError:  # a list nested ~1000 deep
            return "[[[...]]] (nested too deeply to show)"
        if len(text) <= self.limit:
            return text
        count = f" ({len(self.value)} values)" if isinstance(self.value, (list, dict)) else ""
        return text[:self.limit - 20].rsplit(",", 1)[0] + ", ..." + count


def _cut(text: str, limit: int) -> str:
    return text if len(text) <= limit else text[:limit - 4] + " ..."


class _Repeated(ValueError):
    """A JSON object that gives one key twice (json keeps the last value without a word)."""

    def __init__(self, name: str, values: list):
        super().__init__(name)
        self.name, self.values = name, values


class _Values:
    """The values a repeated key was given, as a message shows them: 8, then 16."""

    def __init__(self, values: list):
        self.values = values

    def __repr__(self) -> str:
        return ", then ".join(repr(_Shown(v, 40)) for v in self.values)


def _unique_keys(pairs: list) -> dict:
    out: dict = {}
    for name, value in pairs:
        if name in out:
            raise _Repeated(name, [out[name], value])
        out[name] = value
    return out


def _families() -> dict:
    from codesign.optics.masks import FAMILIES, families

    families()  # every family registered
    return FAMILIES


def record_keys(kind: str) -> set[str]:
    """Every key a record of family ``kind`` may hold (its Spec's other keys, e.g. preset or strategy, are how a
    config builds a mask, never part of a design: refused, as a record's every key is used)."""
    cls = _families()[kind]
    return {"kind", "levels", "optics", *cls.record_values, *cls.record_settings, *FIGURE_KEYS, *PARTIAL_KEYS}


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _read(path: Any, key: str, allowed: str) -> Any:
    """The JSON in the file at ``path``: a regular file of at most MAX_RECORD_BYTES, each object's keys unique,
    nested no deeper than Python reads; ConfigError naming ``key`` otherwise."""
    if not isinstance(path, (str, os.PathLike)):
        raise ConfigError(key, path, allowed)
    if not os.fspath(path).strip():  # Path('') is '.', which was refused as "a directory"
        raise ConfigError(key, path, f"{allowed}; an empty path names no file (null for none)")
    file = Path(path).expanduser()
    try:
        info = file.stat()
    except FileNotFoundError:
        raise ConfigError(key, path, f"{allowed}; no such file") from None
    except OSError as err:
        raise ConfigError(key, path, f"{allowed}; cannot be read ({err.strerror})") from None
    if not stat.S_ISREG(info.st_mode):  # a directory, a FIFO, /dev/zero: never read
        what = "a directory" if stat.S_ISDIR(info.st_mode) else f"{special_file(file)}, not a regular file"
        raise ConfigError(key, path, f"{allowed}; it is {what}")
    too_big = f"{allowed}; it holds {max(info.st_size, MAX_RECORD_BYTES + 1) / 2**20:.1f} MiB, more than any " \
              f"mask record (at most {MAX_RECORD_BYTES // 2**20} MiB: a pixel record of ~2.8 million phases): not read"
    if info.st_size > MAX_RECORD_BYTES:
        raise ConfigError(key, path, too_big)
    try:
        with open(file, "rb") as f:
            raw = f.read(MAX_RECORD_BYTES + 1)
    except OSError as err:
        raise ConfigError(key, path, f"{allowed}; cannot be read ({err.strerror})") from None
    if len(raw) > MAX_RECORD_BYTES:  # it grew since stat
        raise ConfigError(key, path, too_big)
    if raw.startswith(GZIP_MAGIC):
        raw = _unpack(raw, path, key, allowed)
    return _decode(raw, path, key, allowed)


def _unpack(raw: bytes, path: Any, key: str, allowed: str) -> bytes:
    """The JSON text of a gzip-compressed record, at most MAX_RECORD_BYTES of it (a few KiB of gzip can unpack to
    gigabytes, so the bound holds for what it unpacks to, not only for the file)."""
    try:
        with gzip.GzipFile(fileobj=BytesIO(raw)) as f:
            text = f.read(MAX_RECORD_BYTES + 1)
    except (OSError, EOFError, zlib.error) as err:  # not gzip after its first bytes, cut short, corrupt
        raise ConfigError(key, path, f"{allowed}; cannot be unpacked as gzip ({err})") from None
    if len(text) > MAX_RECORD_BYTES:
        raise ConfigError(key, path, f"{allowed}; it unpacks to more than any mask record (at most "
                          f"{MAX_RECORD_BYTES // 2**20} MiB: a pixel record of ~2.8 million phases): not read")
    return text


def _decode(raw: bytes, path: Any, key: str, allowed: str) -> Any:
    try:
        return json.loads(raw, object_pairs_hook=_unique_keys)
    except _Repeated as dup:
        raise ConfigError(f"{key} {path}: {_cut(dup.name, 60)}", _Values(dup.values), "given more than once: a "
                          "record's keys must be unique (which value is meant cannot be told)") from None
    except RecursionError:
        raise ConfigError(key, path, f"{allowed}; it nests lists or objects deeper than Python reads (a mask "
                          f"record nests two levels)") from None
    except json.JSONDecodeError as err:
        raise ConfigError(key, path, f"{allowed}; cannot be read as JSON ({err})") from None
    except UnicodeDecodeError:
        raise ConfigError(key, path, f"{allowed}; cannot be read as JSON (it is not UTF-8 text)") from None
    except ValueError as err:  # e.g. an integer of more than 4300 digits
        raise ConfigError(key, path, f"{allowed}; cannot be read as JSON ({str(err).split(':')[0]})") from None


def load_record(path: Any, key: str, allowed: str) -> Record:
    """The contents of a mask record at ``path``, every key used or refused; ConfigError naming ``key``
    otherwise: about the file as a whole, its message starts with ``allowed`` (what ``key`` accepts) and says what
    is wrong; about one of its values, it names ``key``, the file and the record's key (``mask.init FILE: levels =
    1: ...``) with the rule of the config key the value stands for."""
    data = _read(path, key, allowed)
    kind = data.get("kind") if isinstance(data, dict) else None
    families = _families()
    if not isinstance(kind, str) or kind not in families:
        raise ConfigError(key, path, f"{allowed}; the file holds kind {_Shown(kind)!r}, not a mask family "
                          f"({', '.join(sorted(families))})")
    values = families[kind].record_values
    unknown = sorted(set(data) - record_keys(kind))
    if unknown:
        raise ConfigError(key, path, f"{allowed}; its key(s) {_cut(', '.join(unknown), 200)} are not "
                          f"keys of a {kind} record (allowed: {', '.join(sorted(record_keys(kind)))})")
    bad = [name for name, what in values.items()
           if not (what == "number" and _number(data.get(name))
                   or what == "list" and isinstance(data.get(name), list) and data[name]
                   and all(map(_number, data[name])))]
    if kind == "halfring":
        r, theta = data.get("r"), data.get("theta")
        if bad or len(r) != len(theta):
            raise ConfigError(key, path, f"{allowed}; its r and theta must be non-empty lists of numbers of equal "
                              f"length (got {_Shown(r)!r} and {_Shown(theta)!r})")
    elif bad:
        raise ConfigError(key, path, f"{allowed}; a {kind} record needs {', '.join(values)} "
                          f"(missing or not numbers: {', '.join(bad)})")
    numbers = [v for name in values for v in (data[name] if isinstance(data[name], list)
                                                           else [data[name]])]
    if not all(math.isfinite(v) for v in numbers):  # json reads NaN / Infinity: name the file, not mask.r[i]
        what = f"its r and theta hold NaN or Infinity (got {_Shown(data['r'])!r} and {_Shown(data['theta'])!r})" \
            if kind == "halfring" else "its values hold NaN or Infinity"
        raise ConfigError(key, path, f"{allowed}; {what}")
    with _named(key, path):
        _check_values(data, families[kind])
    _note_partial(data, key, path)
    return Record(data, path)


_NOTED: set = set()  # the partial records already named (a run may read one record twice)


def _note_partial(data: dict, key: str, path: Any) -> None:
    """A partial record (PARTIAL_KEYS: the best point of a search that did not finish) is read with a warning,
    once per file, so that it is never taken for a finished design."""
    if data.get("partial") and str(path) not in _NOTED:
        _NOTED.add(str(path))
        logging.getLogger("codesign").warning("%s=%s is a PARTIAL record: the best point of a search that did not "
                                              "finish (%s), not a finished design", key, path, data["stop_reason"])


@contextmanager
def _named(key: str, path: Any):
    """A ConfigError about a record's key (raised with the prefix _FIELD) named as coming from the file."""
    try:
        yield
    except ConfigError as err:
        raise ConfigError(err.key.replace(f"{_FIELD}.", f"{key} {path}: "), _Shown(err.value),
                          err.allowed.replace(f"{_FIELD}.", "")) from None


def _check_values(data: dict, cls) -> None:
    """Every value of a record by the rules of the config key it stands for: levels (mask.levels), the figures
    (numbers or flags), optics (the optics.* keys) and the family's values and settings (its check_record)."""
    require_levels(f"{_FIELD}.levels", data.get("levels"))
    for name in FIGURE_KEYS:
        value = data.get(name)
        if value is None:
            continue
        if name in FLAG_KEYS and not isinstance(value, bool):
            raise ConfigError(f"{_FIELD}.{name}", value, "must be true, false or null")
        if name not in FLAG_KEYS:
            require_number(f"{_FIELD}.{name}", value)
    if not isinstance(data.get("partial"), (bool, type(None))):  # 1 == True: not a flag
        raise ConfigError(f"{_FIELD}.partial", data["partial"], "must be true, false or null")
    if not isinstance(data.get("stop_reason", ""), (str, type(None))):
        raise ConfigError(f"{_FIELD}.stop_reason", data["stop_reason"], "must be a text or null")
    if (data.get("partial") is True) != (data.get("stop_reason") is not None):  # the flag and its reason go together
        raise ConfigError(f"{_FIELD}.partial", data.get("partial"), "a partial record (an interrupted search's) "
                          "holds \"partial\": true and its \"stop_reason\" (a text); a finished one neither")
    optics = data.get("optics")
    if optics is not None:
        if not isinstance(optics, dict):
            raise ConfigError(f"{_FIELD}.optics", optics, "must be the optics the design was made for: a mapping of "
                              "optics keys (wavelength_m, focal_length_m, ...)")
        OpticsSpec.from_config(optics, prefix=f"{_FIELD}.optics")
    cls.check_record(data, _FIELD)


def check_design_optics(record: Mapping[str, Any], optics: OpticsSpec, key: str, path: Any) -> None:
    """ConfigError when ``record`` was designed for other optics (DESIGN_OPTICS) than ``optics``, naming both
    values (a record without optics, written before records held them, is taken as it is)."""
    made = record.get("optics") or {}
    for name in DESIGN_OPTICS:
        if name in made and not math.isclose(made[name], getattr(optics, name), rel_tol=1e-9):
            raise ConfigError(f"{key} {path}: optics.{name}", made[name], f"the design was made for these optics, "
                              f"not the configured optics.{name} = {getattr(optics, name)!r}: set "
                              f"optics.{name}={made[name]!r} to use it as designed, or design one for these optics")
    for name, what in (("wrap_waves", "the surface it was designed as"),
                       ("laser_wavelengths_m", "the laser lines it was designed for")):
        if name in made and _same(made[name]) != _same(getattr(optics, name)):
            logging.getLogger("codesign.mask").warning(
                "%s %s: optics.%s = %r is %s; this run uses %r: off the design wavelength the mask then behaves "
                "otherwise than it was designed to (set optics.%s=%s to keep it)", key, path, name, made[name], what,
                getattr(optics, name), name, "null" if made[name] is None else made[name])


def _same(value):
    """A record's or a spec's value in one form (lists as tuples of floats) for comparison."""
    return tuple(float(v) for v in value) if isinstance(value, (list, tuple)) else value


def init_allowed(kind: Any) -> str:
    """What mask.init of a ``kind`` mask accepts, as a message says it."""
    cls = _families().get(kind) if isinstance(kind, str) else None
    named = NAMED_STARTS if cls is not None and cls.fits_phases else ()
    return f"must be {'one of ' + ', '.join(named) + ' or ' if named else 'null or '}{RECORD_PATH}"


def check_mask_init(settings: Mapping[str, Any], optics_settings: Mapping[str, Any], prefix: str = "mask") -> None:
    """The record ``mask.init`` names, if any, read whole and made for the configured optics; for the runner, before
    any work (build_mask reads it again, to build the mask)."""
    init = settings.get("init")
    if not isinstance(init, (str, os.PathLike)) or init in NAMED_STARTS:
        return
    kind = settings.get("basis", "pixel") if settings.get("kind") == "freeform" else settings.get("kind")
    record = load_record(init, f"{prefix}.init", init_allowed(kind))
    check_design_optics(record, OpticsSpec.from_config(optics_settings), f"{prefix}.init", init)


def optics_record(spec) -> dict:
    """The OpticsSpec's fields (SI units) as a JSON-ready dict."""
    return {f.name: getattr(spec, f.name) for f in fields(spec) if f.name != "prefix"}


def design_record(mask, spec, figures: dict | None = None) -> dict:
    """``mask.record()`` plus ``optics`` (the spec it was evaluated on) and the scalar figures of merit (names from
    FIGURE_KEYS: what mask.init reads back accepts exactly those)."""
    other = sorted(set(figures or {}) - set(FIGURE_KEYS) - set(PARTIAL_KEYS))
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
