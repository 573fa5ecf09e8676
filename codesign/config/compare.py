"""Two configurations compared key by key, and the differences said with both values: one home for what a
restart, a resume, a warm start and a finished run's rerun tell the user (codesign/experiments/rundir.py,
codesign/experiments/resume.py, codesign/train/stage_settings.py)."""
from __future__ import annotations

from typing import Any, Mapping

ABSENT = "(absent)"  # the value shown for a key one side lacks


def flat_keys(node: Any, prefix: str = "") -> dict:
    """A nested mapping (plain containers) as {dotted key: leaf}; an empty mapping or a non-mapping is one leaf."""
    if isinstance(node, Mapping) and node:
        return {k: v for key, value in node.items() for k, v in flat_keys(value, f"{prefix}{key}.").items()}
    return {prefix[:-1]: node}


def covered(key: str, prefixes: tuple) -> bool:
    """Whether dotted ``key`` is one of ``prefixes`` or lies under one (a prefix 'trainer' covers its whole block)."""
    return any(key == p or key.startswith(p + ".") for p in prefixes)


def differences(old: dict, new: dict, ignored: tuple = ()) -> list[tuple[str, Any, Any]]:
    """(key, old value, new value), sorted by key, for every dotted key of either flat mapping whose values differ,
    the ``ignored`` prefixes left out; a key one side lacks shows as ABSENT."""
    keys = sorted(k for k in set(old) | set(new) if not covered(k, ignored))
    return [(k, old.get(k, ABSENT), new.get(k, ABSENT)) for k in keys if old.get(k, ABSENT) != new.get(k, ABSENT)]


def described(differ: list[tuple[str, Any, Any]], shown: int, quoted: bool = True) -> str:
    """'KEY = OLD there, NEW here; ...' for the first ``shown`` differences, then how many more (values as repr
    with ``quoted``, else as str)."""
    fmt = repr if quoted else str
    each = "; ".join(f"{k} = {fmt(o)} there, {fmt(n)} here" for k, o, n in differ[:shown])
    return each + (f"; and {len(differ) - shown} more key(s)" if len(differ) > shown else "")
