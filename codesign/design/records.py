"""Design records: a mask's JSON record (codesign/optics/masks/records.py) with the optics it was designed for and
its figures of merit, as written by mask_search (best_mask.json), joint (learned_mask.json) and psf (mask.json)."""
from __future__ import annotations

from dataclasses import fields
from pathlib import Path

from codesign.io import files as io


def optics_record(spec) -> dict:
    """The OpticsSpec's fields (SI units) as a JSON-ready dict."""
    return {f.name: getattr(spec, f.name) for f in fields(spec) if f.name != "prefix"}


def design_record(mask, spec, figures: dict | None = None) -> dict:
    """``mask.record()`` plus ``optics`` (the spec it was evaluated on) and the scalar figures of merit (names from
    FIGURE_KEYS: what mask.init reads back accepts exactly those)."""
    from codesign.optics.masks.records import FIGURE_KEYS

    other = sorted(set(figures or {}) - set(FIGURE_KEYS))
    if other:  # a writer's new figure must be registered, or the record it writes would be refused when read
        raise ValueError(f"design_record: figure(s) {', '.join(other)} not in FIGURE_KEYS "
                         f"(codesign/optics/masks/records.py)")
    scalars = {k: v for k, v in (figures or {}).items() if isinstance(v, (int, float, str, bool)) or v is None}
    return {**mask.record(), "optics": optics_record(spec), **scalars}


def write_record(path: Path, mask, spec, figures: dict | None = None) -> dict:
    """Write ``design_record`` atomically to ``path``; returns it."""
    record = design_record(mask, spec, figures)
    io.write_json(path, record)
    return record
