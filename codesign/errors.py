"""Errors raised for bad user input, with the offending key and what is allowed."""
from __future__ import annotations

import math
import os
import stat
from typing import Any, Sequence

import numpy as np


class ConfigError(ValueError):
    """A configuration value (or input) is wrong. The message names the key, the value and what is allowed."""

    def __init__(self, key: str, value: Any, allowed: str):
        self.key, self.value, self.allowed = key, value, allowed
        super().__init__(f"{key} = {value!r}: {allowed}")


def plain_number(value: Any) -> Any:
    """A numpy scalar (np.float32, np.int64) or 0-d array as the Python number it holds, anything else unchanged:
    a number computed with numpy is a number (np.float32(1e6) was refused as "must be a finite number"); a numpy
    bool becomes a bool, which the checks still refuse."""
    if isinstance(value, np.generic) or (isinstance(value, np.ndarray) and value.ndim == 0):
        return value.item()
    return value


def require_number(key: str, value: Any, *, lo: float | None = None, hi: float | None = None,
                   lo_open: bool = False, hi_open: bool = False, integer: bool = False) -> float:
    """Check that ``value`` is a finite (integer) number in the given range; return it, else raise ConfigError."""
    kind = "an integer" if integer else "a finite number"
    lo_s = "" if lo is None else f"{'>' if lo_open else '>='} {lo:g}"
    hi_s = "" if hi is None else f"{'<' if hi_open else '<='} {hi:g}"
    allowed = f"must be {kind}" + (f" {lo_s}" if lo_s else "") + (" and" if lo_s and hi_s else "") + \
        (f" {hi_s}" if hi_s else "")
    value = plain_number(value)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(key, value, allowed)
    if integer and not float(value).is_integer():
        raise ConfigError(key, value, allowed)
    if not math.isfinite(value):
        raise ConfigError(key, value, allowed)
    if lo is not None and (value <= lo if lo_open else value < lo):
        raise ConfigError(key, value, allowed)
    if hi is not None and (value >= hi if hi_open else value > hi):
        raise ConfigError(key, value, allowed)
    return int(value) if integer else float(value)


def require_choice(key: str, value: Any, choices: tuple[str, ...]) -> str:
    """``value`` when it is one of ``choices``, else ConfigError naming ``key`` and the choices."""
    if value not in choices:
        raise ConfigError(key, value, f"must be one of {', '.join(choices)}")
    return value


def require_list(key: str, value: Any, allowed: str) -> list:
    """``value`` as a list when it is a list or tuple (an OmegaConf ListConfig counts); else ConfigError with
    ``allowed``. A bare number or string where a list belongs would otherwise fail deep inside with a TypeError
    (or, for a string, be read one character at a time)."""
    if isinstance(value, np.ndarray) and value.ndim == 1:  # a numpy vector is a list of numbers
        return value.tolist()
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        raise ConfigError(key, value, allowed)
    return list(value)


def require_numbers(key: str, value: Any, allowed: str, length: int | None = None, **bounds: Any) -> list[float]:
    """A config list of finite numbers: ``require_list``, then ``length`` (ConfigError with ``allowed``), then
    each element through ``require_number`` with ``bounds``, its error naming ``key[i]``."""
    items = require_list(key, value, allowed)
    if length is not None and len(items) != length:
        raise ConfigError(key, items, allowed)
    return [require_number(f"{key}[{i}]", v, **bounds) for i, v in enumerate(items)]


def refuse_repeats(key: str, values: Sequence) -> None:
    """ConfigError naming ``key`` when a value of list ``values`` appears twice (a laser strength listed twice was
    evaluated twice, its rows duplicated)."""
    seen: set = set()
    for value in values:
        if value in seen:
            raise ConfigError(key, list(values), f"lists {value:g} twice: give each value once")
        seen.add(value)


def special_file(path: Any) -> str | None:
    """What stands at ``path`` when it exists but is neither a regular file nor a folder ("a character device",
    "a named pipe (FIFO)", ...), else None. Found by os.stat only, never by opening it: opening a named pipe blocks
    until a writer comes, and /dev/zero never ends. Every path key calls it, so that a device or a pipe is named
    as such (it was "no such file", the path being there)."""
    try:
        mode = os.stat(os.path.expanduser(os.fspath(path))).st_mode
    except (OSError, TypeError, ValueError):
        return None
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return None
    kinds = ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
             (stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISSOCK, "a socket"))
    return next((name for test, name in kinds if test(mode)), "not a regular file")


class OutputWriteError(OSError):
    """An output file could not be written; the file that was there before (if any) is unchanged."""


def round_up(x: float, digits: int = 3) -> float:
    """``x`` > 0 rounded up to ``digits`` significant digits: a bound an error message prints (%.{digits}g) stays a
    true bound, so the advice holds for the value it names."""
    unit = 10.0 ** (math.floor(math.log10(x)) - (digits - 1))
    return math.ceil(x / unit * (1 - 1e-12)) * unit


def round_down(x: float, digits: int = 3) -> float:
    """``x`` > 0 rounded down to ``digits`` significant digits (see round_up)."""
    unit = 10.0 ** (math.floor(math.log10(x)) - (digits - 1))
    return math.floor(x / unit * (1 + 1e-12)) * unit
