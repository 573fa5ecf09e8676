"""One name per figure in metrics.json and results files, and how the names of older files map onto today's.

Today's names: ``psnr`` / ``ssim`` are the plain scores, ``psnr_matched`` / ``ssim_matched`` the scores after the
per-image least-squares gain and offset match; a ``_published`` suffix (or infix, before a condition) marks the
published system's figure; laser strengths are written ``alpha_l_0``, ``alpha_l_1e3``, ``alpha_l_1e6``,
``alpha_l_2.5e5`` in keys and file names (codesign.data.params.alpha_tag).

Until issue 39 the matched scores were ``*_affine``, the published system's figures ``*_baseline`` (which clashed
with ``+experiment=baseline``) and simulate wrote ``alpha_l_1e+06``. ``upgrade`` renames those keys (at any depth)
and says which it renamed; ``python -m codesign.io.metric_names FILE...`` rewrites files in place (every file read and
checked before any is rewritten, each atomically, NaN / Infinity kept; ``--check`` only lists what it would rename
and exits 1 when anything is old; a file that cannot be read or renamed: exit 2, nothing rewritten).
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

# old word -> today's word, applied to whole underscore-separated words of a key but its first
WORDS = {"affine": "matched", "baseline": "published"}
_PLUS_EXPONENT = re.compile(r"(alpha_l_\d+(?:\.\d+)?)e\+0*(\d+)")


def new_name(key: str) -> str:
    """Today's name of a metrics key (unchanged when it is already today's)."""
    key = _PLUS_EXPONENT.sub(r"\1e\2", key)
    parts = key.split("_")
    # a word is renamed only as a metric qualifier: after the first word (``baseline_*`` keys name the experiment)
    return "_".join(p if i == 0 else WORDS.get(p, p) for i, p in enumerate(parts))


def upgrade(obj: Any) -> tuple[Any, dict[str, str]]:
    """``obj`` with every dict key at any depth under today's name, and {old: new} of the keys renamed."""
    renamed: dict[str, str] = {}

    def walk(x: Any) -> Any:
        if isinstance(x, dict):
            out = {}
            for k, v in x.items():
                n = new_name(k) if isinstance(k, str) else k
                if n != k:
                    renamed[k] = n
                    if n in x:
                        raise ValueError(f"key {k!r} would become {n!r}, which the same object already holds")
                out[n] = walk(v)
            return out
        if isinstance(x, list):
            return [walk(v) for v in x]
        return x

    return walk(obj), renamed


def read_metrics(path: Path) -> dict:
    """A metrics or results JSON file under today's names, whichever version wrote it."""
    return upgrade(json.loads(Path(path).read_text()))[0]


PROG = "python -m codesign.io.metric_names"


def _upgraded(path: Path) -> tuple[Any, dict[str, str]]:
    """(the file's JSON under today's names, {old: new}); ValueError with why the file cannot be rewritten."""
    if path.is_dir():
        raise ValueError("is a folder, not a JSON file")
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ValueError("no such file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"cannot be read ({getattr(err, 'strerror', None) or err})") from None
    try:
        data = json.loads(text)  # NaN and Infinity read as floats, and written back as they were (allow_nan)
    except json.JSONDecodeError as err:
        raise ValueError(f"is not JSON ({err})") from None
    try:
        return upgrade(data)
    except ValueError as err:  # an old key and its new name in one object
        raise ValueError(f"cannot be renamed: {err}") from None


def _rewrite(path: Path, data: Any) -> None:
    """``data`` written to ``path`` atomically, in the file's key order, NaN / Infinity kept (io.write_json would
    write them as null)."""
    from codesign.io.files import atomic_write_bytes

    text = json.dumps(data, indent=2, allow_nan=True) + "\n"
    atomic_write_bytes(path, lambda f: f.write(text.encode()))


def main(argv: list[str] | None = None) -> int:
    """Rename the old metric names in the given JSON files (``--check``: only list them, exit 1 if any); returns the
    exit status: 2, nothing rewritten, when any file cannot be read or renamed (every file is checked first)."""
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+", type=Path, help="JSON files (metrics.json, results files)")
    ap.add_argument("--check", action="store_true", help="list what would be renamed; exit 1 if anything would")
    args = ap.parse_args(argv)
    upgraded, bad = [], []
    for path in args.files:
        try:
            upgraded.append((path, *_upgraded(path)))
        except ValueError as err:
            bad.append(f"{PROG}: {path}: {err}")
    if bad:
        for line in bad:
            print(f"{line}; nothing was rewritten (every file is checked before any is)", file=sys.stderr)
        return 2
    old = 0
    for path, data, renamed in upgraded:
        if not renamed:
            continue
        old += 1
        print(f"{path}: " + ", ".join(f"{k} -> {v}" for k, v in sorted(renamed.items())))
        if not args.check:
            _rewrite(path, data)
    return 1 if args.check and old else 0


if __name__ == "__main__":
    sys.exit(main())
