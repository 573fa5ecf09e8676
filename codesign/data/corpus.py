"""The training corpus of real photographs (``data/corpus/``): its manifest, its verification and its rebuild.

The corpus holds a few hundred natural photographs (landscape, water, architecture, people, animals, plants, texture,
night, indoor, aerial, ...) taken from Debian packages and public GitHub repositories whose licences allow modified
versions to be redistributed. Each one was converted to 8-bit grayscale and downscaled; ``data/corpus/manifest.json``
records, per PNG, where its original comes from (package and version, or repository and commit, and the path inside),
the original's sha256 and size, the author, the licence and what the photograph shows. ``data/corpus/README.md``
gives the counts, the attributions, the excluded sources and the near-duplicate check.

Why a module and not only a folder: training data whose provenance cannot be checked is a liability. ``verify``
checks that the folder is exactly what the manifest says (no file missing, none unlisted, every sha256 matching),
that no source reserved for independent evaluation slipped in and that every licence is one that allows
redistribution of modified versions. ``build`` re-creates every PNG from the originals, checking each original's
sha256 first, so that the corpus can be rebuilt (and audited) without trusting the committed files.

    python -m codesign.data.corpus verify data/corpus
    python -m codesign.data.corpus fetch-debs --originals DIR      # Debian originals + the git commands to run
    python -m codesign.data.corpus build --originals DIR --out data/corpus

Only Pillow and numpy are used; nothing is downloaded at import time.
"""
from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

# The processing every PNG went through (also written into the manifest, so the manifest describes itself).
SHORT_SIDE = 384            # pixels of the short side after resizing
MAX_ASPECT = 16 / 9         # longer/shorter side ratio kept at most; wider (or taller) originals are centre-cropped
LUMA = (0.299, 0.587, 0.114)

# SPDX-like short names of the licences accepted: each allows modified versions to be redistributed (public domain,
# CC0, CC-BY(-SA), GPL/LGPL/BSD/MIT-style, GFDL, and the Unsplash/Pexels/Pixabay licences). No NC, no ND.
ALLOWED_LICENCES = frozenset({
    "public-domain", "CC0-1.0", "CC-BY-2.0", "CC-BY-3.0", "CC-BY-4.0", "CC-BY-SA-2.0", "CC-BY-SA-3.0",
    "CC-BY-SA-4.0", "GPL-2.0-only", "GPL-2.0-or-later", "GPL-3.0-or-later", "LGPL-2.1-or-later", "BSD-2-Clause",
    "MIT", "WTFPL", "GFDL", "Unsplash", "Pexels", "Pixabay",
})

# Sources reserved for independent evaluation: none of their files may be in the corpus. Matched (case-insensitive)
# against the manifest's "source" field, e.g. "deb:lomiri-wallpapers" or "git:KDE/plasma-workspace-wallpapers".
FORBIDDEN_SOURCE_PATTERNS = (
    r"lomiri-wallpapers", r"ubuntu", r"plasma-workspace-wallpapers", r"lxqt-themes", r"kubuntu", r"xubuntu",
)

# The originals of the held-out photographs (codesign/data/heldout/SOURCES.md) and of the shared example scenes
# (mate-backgrounds' nature/ folder): the corpus must contain none of them. (source, path suffix) pairs.
RESERVED_ORIGINALS = (
    ("ukui-wallpapers", "backgrounds/bluebird.jpg"), ("ukui-wallpapers", "backgrounds/bridgecity.jpg"),
    ("ukui-wallpapers", "backgrounds/horse.jpg"), ("ukui-wallpapers", "backgrounds/sky.jpg"),
    ("ukui-wallpapers", "backgrounds/sunf.jpg"),
    *(("deepin-wallpapers", name) for name in (
        "ashim-d-silva-WeYamle9fDM-unsplash.jpg", "cristina-gottardi-wndpWTiDuT0-unsplash.jpg",
        "francesco-ungaro-1fzbUyzsHV8-unsplash.jpg", "jeremy-bishop-2e3hgvDnCpM-unsplash.jpg",
        "joshua-coleman-KzPefInJW58-unsplash.jpg", "luca-micheli-ruWkmt3nU58-unsplash.jpg",
        "lucian-dachman-qxO2PBn7eKU-unsplash.jpg", "luke-stackpoole-mStq-dtsXCQ-unsplash.jpg",
        "willian-justen-de-vasconcellos-ASKGjAeIY_U-unsplash.jpg", "wolfgang-hasselmann-WrVvYxq11Yk-unsplash.jpg",
        "zetong-li-TbHYpbi_Gbc-unsplash.jpg")),
    ("mate-backgrounds", "backgrounds/mate/nature/"),
)

# The committed corpus: data/corpus/ at the repository root (an editable install, as install.sh makes).
DEFAULT_FOLDER = Path(__file__).resolve().parents[2] / "data" / "corpus"
NAME_RE = re.compile(r"^[a-z0-9_]+/[a-z0-9_]+\.png$")
ENTRY_FIELDS = ("file", "sha256", "source", "source_version_or_commit", "original_path", "original_sha256",
                "original_size", "author", "licence", "content")


def processing_description() -> dict:
    """The processing recorded in the manifest: what was done to every original, in order."""
    return {
        "orientation": "EXIF orientation applied (PIL.ImageOps.exif_transpose)",
        "colour": "converted to RGB (alpha dropped; palette/grey expanded), no ICC conversion; "
                  "luma Y = 0.299 R + 0.587 G + 0.114 B in float64",
        "crop": f"centre crop of the long side to at most {MAX_ASPECT:.4f} (16:9) times the short side",
        "resize": f"short side to {SHORT_SIDE} px, long side round(long * {SHORT_SIDE} / short); Pillow Lanczos "
                  "on the float32 image (mode F)",
        "quantisation": "rounded (numpy.rint, halves to even), clipped to 0..255, uint8",
        "output": "8-bit grayscale PNG (mode L), optimize=True, no metadata",
        "short_side": SHORT_SIDE, "max_aspect": "16:9",
    }


def luma(img) -> np.ndarray:
    """Float64 luma of a PIL image (any mode): the Rec. 601 weights used throughout codesign's photographs."""
    rgb = np.asarray(img.convert("RGB"), dtype=np.float64)
    return LUMA[0] * rgb[..., 0] + LUMA[1] * rgb[..., 1] + LUMA[2] * rgb[..., 2]


def crop_box(width: int, height: int) -> tuple[int, int, int, int]:
    """(left, top, right, bottom) of the centred region whose aspect ratio is at most MAX_ASPECT."""
    if width >= height:
        keep = min(width, int(height * MAX_ASPECT))
        left = (width - keep) // 2
        return left, 0, left + keep, height
    keep = min(height, int(width * MAX_ASPECT))
    top = (height - keep) // 2
    return 0, top, width, top + keep


def process(src) -> "Image.Image":
    """The corpus processing of one original (a path or a file object): returns the 8-bit grayscale PIL image.

    Luma is computed in floating point before any resampling, so the downscale averages light, not gamma-encoded
    colour channels separately; the float image is resized with Lanczos (anti-aliased) and only then quantised.
    """
    from PIL import Image, ImageOps

    Image.MAX_IMAGE_PIXELS = None  # some originals are 8k panoramas; they come from trusted, hashed sources
    with Image.open(src) as opened:
        img = ImageOps.exif_transpose(opened)
        y = luma(img)
    h, w = y.shape
    left, top, right, bottom = crop_box(w, h)
    y = y[top:bottom, left:right]
    h, w = y.shape
    short = min(h, w)
    size = (SHORT_SIDE, round(h * SHORT_SIDE / short)) if w == short else (round(w * SHORT_SIDE / short), SHORT_SIDE)
    small = Image.fromarray(y.astype(np.float32), mode="F").resize(size, Image.LANCZOS)
    out = np.clip(np.rint(np.asarray(small, dtype=np.float64)), 0, 255).astype(np.uint8)
    return Image.fromarray(out, mode="L")


def png_bytes(img) -> bytes:
    """The PNG encoding used for every corpus file: optimize=True, no text/ICC/EXIF chunks."""
    buf = io.BytesIO()
    img.save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def sha256_file(path: Path) -> str:
    """Hex sha256 of a file, read in blocks (some originals are tens of MB)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def load_manifest(folder) -> dict:
    """The corpus manifest (``FOLDER/manifest.json``): {"processing": {...}, "files": [entry, ...]}."""
    path = Path(folder) / "manifest.json"
    with open(path, encoding="utf-8") as f:
        manifest = json.load(f)
    if not isinstance(manifest, dict) or not isinstance(manifest.get("files"), list):
        raise ValueError(f"{path}: expected a JSON object with a 'files' list")
    return manifest


def _entry_problems(entry: dict) -> list[str]:
    """Problems of one manifest entry on its own: missing fields, bad name, forbidden source, licence, reserved file."""
    name = entry.get("file", "?")
    problems = [f"{name}: manifest entry lacks '{k}'" for k in ENTRY_FIELDS if not entry.get(k)]
    if not NAME_RE.match(name):
        problems.append(f"{name}: name must be <source>/<name>.png in [a-z0-9_]")
    source = str(entry.get("source", ""))
    for pattern in FORBIDDEN_SOURCE_PATTERNS:
        if re.search(pattern, source, flags=re.I):
            problems.append(f"{name}: source '{source}' is reserved for independent evaluation ({pattern})")
    if entry.get("licence") not in ALLOWED_LICENCES:
        problems.append(f"{name}: licence '{entry.get('licence')}' is not in the allowed set")
    path = str(entry.get("original_path", ""))
    for package, suffix in RESERVED_ORIGINALS:
        if package in source and (path.endswith(suffix) or (suffix.endswith("/") and suffix in path)):
            problems.append(f"{name}: original {path} of {source} is a held-out/example-scene original")
    return problems


def verify(folder) -> list[str]:
    """Every problem of the corpus folder against its manifest (empty list = consistent).

    Reports: manifest entries whose file is missing, PNG files not in the manifest, sha256 mismatches, duplicate
    names or duplicate originals, forbidden sources, licences outside ALLOWED_LICENCES and held-out originals.
    """
    folder = Path(folder)
    try:
        manifest = load_manifest(folder)
    except (OSError, ValueError) as err:
        return [f"manifest: {err}"]
    problems, seen, originals = [], set(), set()
    for entry in manifest["files"]:
        name = entry.get("file", "?")
        if name in seen:
            problems.append(f"{name}: listed twice in the manifest")
        seen.add(name)
        key = (entry.get("source"), entry.get("original_sha256"))
        if entry.get("original_sha256") and key in originals:
            problems.append(f"{name}: same original as another entry ({entry.get('original_sha256')[:16]})")
        originals.add(key)
        problems += _entry_problems(entry)
        path = folder / name
        if not path.is_file():
            problems.append(f"{name}: listed in the manifest but missing from {folder}")
        elif sha256_file(path) != entry.get("sha256"):
            problems.append(f"{name}: sha256 mismatch (file {sha256_file(path)[:16]}, "
                            f"manifest {str(entry.get('sha256'))[:16]})")
    for path in sorted(folder.rglob("*.png")):
        rel = path.relative_to(folder).as_posix()
        if rel not in seen:
            problems.append(f"{rel}: file not in the manifest")
    return problems


def original_location(originals, entry: dict) -> Path:
    """Where ``build`` expects an entry's original under the originals folder.

    DIR/deb/<package>_<version>/<path> for Debian sources, DIR/git/<owner>+<repo>@<commit>/<path> for repositories;
    an entry with a "member" (an image inside a container file, e.g. an Enlightenment .edj) is read from
    <that location>.decc/<member>, which ``fetch-debs`` creates with edje_decc.
    """
    kind, _, name = entry["source"].partition(":")
    if kind == "deb":
        base = Path(originals) / "deb" / f"{name}_{entry['source_version_or_commit']}"
    elif kind == "git":
        base = Path(originals) / "git" / f"{name.replace('/', '+')}@{entry['source_version_or_commit']}"
    else:
        raise ValueError(f"{entry.get('file')}: unknown source kind '{kind}' (expected deb: or git:)")
    path = base / entry["original_path"]
    return path.parent / (path.name + ".decc") / entry["member"] if entry.get("member") else path


def write_atomic(path: Path, data: bytes) -> None:
    """Write through a temporary file in the same folder and rename, so a PNG is never left half-written."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".png")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def build(originals, out, manifest: dict | None = None) -> list[str]:
    """Re-create every PNG of the manifest from the originals; returns the problems (empty = all rebuilt).

    An original whose sha256 differs from the manifest is not processed (its PNG would not be the recorded one).
    The manifest is copied into ``out`` when ``out`` has none, so that ``verify(out)`` then checks the result.
    """
    out = Path(out)
    manifest = manifest if manifest is not None else load_manifest(DEFAULT_FOLDER)
    problems = []
    for entry in manifest["files"]:
        src = original_location(originals, entry)
        if not src.is_file():
            problems.append(f"{entry['file']}: original not found at {src}")
            continue
        if sha256_file(src) != entry["original_sha256"]:
            problems.append(f"{entry['file']}: original {src} has sha256 {sha256_file(src)[:16]}, "
                            f"manifest says {entry['original_sha256'][:16]}")
            continue
        write_atomic(out / entry["file"], png_bytes(process(src)))
    if not (out / "manifest.json").exists():
        (out / "manifest.json").write_text(json.dumps(manifest, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    return problems


def debian_sources(manifest: dict) -> list[tuple[str, str]]:
    """The (package, version) pairs of the manifest's Debian sources, sorted."""
    return sorted({(e["source"].split(":", 1)[1], e["source_version_or_commit"])
                   for e in manifest["files"] if e["source"].startswith("deb:")})


def git_commands(manifest: dict, originals) -> list[str]:
    """Shell commands that lay out the repository originals as ``build`` expects (one bare clone per repository,
    then ``git archive`` of the needed paths of each commit). Printed, not run: they need network access."""
    by_commit: dict[tuple[str, str], list[str]] = {}
    for e in manifest["files"]:
        if e["source"].startswith("git:"):
            by_commit.setdefault((e["source"][4:], e["source_version_or_commit"]), []).append(e["original_path"])
    lines, cloned = [], set()
    for (repo, commit), paths in sorted(by_commit.items()):
        bare = Path(originals) / "git" / f"{repo.replace('/', '+')}.git"
        if repo not in cloned:
            lines.append(f"git clone --bare https://github.com/{repo} '{bare}'")
            cloned.add(repo)
        dest = Path(originals) / "git" / f"{repo.replace('/', '+')}@{commit}"
        quoted = " ".join("'" + p.replace("'", "'\\''") + "'" for p in sorted(set(paths)))
        lines.append(f"mkdir -p '{dest}' && git -C '{bare}' archive {commit} -- {quoted} | tar -x -C '{dest}'")
    return lines


def fetch_debs(originals, manifest: dict) -> list[str]:
    """Download and unpack the Debian originals with apt-get/dpkg-deb (Debian's configured archive), decode the
    members of container files with edje_decc, and return the git commands still to run for the other sources."""
    originals = Path(originals)
    cache = originals / "debs"
    cache.mkdir(parents=True, exist_ok=True)
    for package, version in debian_sources(manifest):
        dest = originals / "deb" / f"{package}_{version}"
        if not dest.is_dir():
            subprocess.run(["apt-get", "download", f"{package}={version}"], cwd=cache, check=True, stdout=sys.stderr)
            deb = max(cache.glob(f"{package}_*.deb"), key=lambda p: p.stat().st_mtime)
            tmp = dest.with_name(dest.name + ".partial")  # unpacked, then renamed: no half-extracted tree
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            subprocess.run(["dpkg-deb", "-x", str(deb), str(tmp)], check=True, stdout=sys.stderr)
            tmp.rename(dest)
    for e in manifest["files"]:
        if e["source"].startswith("deb:") and e.get("member"):
            container = original_location(originals, {**e, "member": None})
            decoded = container.parent / (container.name + ".decc")
            if not (decoded / e["member"]).is_file():
                if shutil.which("edje_decc") is None:
                    raise RuntimeError("edje_decc not found: install Debian's libedje-bin to decode .edj originals")
                decoded.mkdir(parents=True, exist_ok=True)
                subprocess.run(["edje_decc", str(container), "-no-build-sh"], cwd=decoded, check=True,
                               capture_output=True)
    return git_commands(manifest, originals)


def main(argv=None) -> int:
    """Command line: verify FOLDER | fetch-debs --originals DIR | build --originals DIR --out FOLDER."""
    ap = argparse.ArgumentParser(prog="python -m codesign.data.corpus", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    v = sub.add_parser("verify", help="check a corpus folder against its manifest")
    v.add_argument("folder", type=Path)
    f = sub.add_parser("fetch-debs", help="fetch the Debian originals; print the git commands for the others")
    f.add_argument("--originals", type=Path, required=True)
    f.add_argument("--manifest", type=Path, default=None, help="corpus folder whose manifest to use")
    b = sub.add_parser("build", help="re-create the PNGs from the originals")
    b.add_argument("--originals", type=Path, required=True)
    b.add_argument("--out", type=Path, required=True)
    b.add_argument("--manifest", type=Path, default=None, help="corpus folder whose manifest to use")
    a = ap.parse_args(argv)
    if a.cmd == "verify":
        problems = verify(a.folder)
    else:
        manifest = load_manifest(a.manifest or DEFAULT_FOLDER)
        if a.cmd == "fetch-debs":
            print("\n".join(fetch_debs(a.originals, manifest)))
            return 0
        problems = build(a.originals, a.out, manifest)
        problems += verify(a.out) if not problems else []
    for p in problems:
        print(p, file=sys.stderr)
    print(f"{len(problems)} problem(s)" if problems else "ok")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
