"""The training corpus of real photographs (data/corpus/): the committed files match their manifest, no reserved
source or held-out original is in it, every licence allows modified redistribution, ``verify`` names each kind of
inconsistency, and the processing turns an RGB image into the documented luma PNG."""
from __future__ import annotations

import io
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from codesign.data import corpus

REPO = Path(__file__).resolve().parents[2]
CORPUS = REPO / "data" / "corpus"
HELDOUT_SOURCES = REPO / "codesign" / "data" / "heldout" / "SOURCES.md"
SCENES_SOURCES = REPO.parent / "shared" / "data" / "scenes" / "SOURCES.md"


@pytest.fixture(scope="module")
def manifest() -> dict:
    return corpus.load_manifest(CORPUS)


def _reserved_sha_prefixes() -> set[str]:
    """First 16 hex digits of the originals' sha256 listed in the held-out (and, when present, the example-scene)
    SOURCES.md tables: the corpus must not contain any of these originals."""
    prefixes = set()
    for path in (HELDOUT_SOURCES, SCENES_SOURCES):
        if path.is_file():
            prefixes |= set(re.findall(r"\| ([0-9a-f]{16}) \|$", path.read_text(encoding="utf-8"), flags=re.M))
    return prefixes


def test_committed_corpus_matches_its_manifest(manifest):
    files = manifest["files"]
    assert len(files) >= 300
    assert corpus.verify(CORPUS) == []
    on_disk = sorted(p.relative_to(CORPUS).as_posix() for p in CORPUS.rglob("*.png"))
    assert on_disk == sorted(e["file"] for e in files)
    assert manifest["processing"]["short_side"] == corpus.SHORT_SIDE


def test_no_reserved_source_no_held_out_original_and_only_allowed_licences(manifest):
    reserved = _reserved_sha_prefixes()
    assert len(reserved) >= 16  # the held-out table at least
    for e in manifest["files"]:
        assert e["licence"] in corpus.ALLOWED_LICENCES, e["file"]
        assert not any(re.search(p, e["source"], flags=re.I) for p in corpus.FORBIDDEN_SOURCE_PATTERNS), e["file"]
        assert e["original_sha256"][:16] not in reserved, e["file"]
        assert re.fullmatch(r"[0-9a-f]{64}", e["original_sha256"]) and re.fullmatch(r"\d+x\d+", e["original_size"])
        assert min(map(int, e["original_size"].split("x"))) >= 600, e["file"]
        assert e["source"].startswith(("deb:", "git:")) and e["author"] and e["content"], e["file"]


def test_every_file_is_a_grayscale_photograph_of_the_documented_size(manifest):
    for e in manifest["files"][::25]:  # a sample keeps the test fast; verify() already hashed every file
        img = Image.open(CORPUS / e["file"])
        assert img.mode == "L" and min(img.size) == corpus.SHORT_SIDE, e["file"]
        assert max(img.size) <= round(corpus.SHORT_SIDE * corpus.MAX_ASPECT) + 1, e["file"]
        assert np.asarray(img, dtype=np.float64).std() > 5, e["file"]


def _small_corpus(tmp_path: Path, manifest: dict, n: int = 3) -> Path:
    """A copy of the first n corpus files with a manifest listing exactly them."""
    folder = tmp_path / "corpus"
    entries = manifest["files"][:n]
    for e in entries:
        (folder / e["file"]).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(CORPUS / e["file"], folder / e["file"])
    (folder / "manifest.json").write_text(json.dumps({"processing": manifest["processing"], "files": entries}))
    return folder


def test_verify_names_tampered_missing_and_unlisted_files(tmp_path, manifest):
    folder = _small_corpus(tmp_path, manifest)
    assert corpus.verify(folder) == []
    first, second, _ = (e["file"] for e in manifest["files"][:3])
    pixels = np.asarray(Image.open(folder / first)).copy()
    pixels[0, 0] ^= 1
    Image.fromarray(pixels, mode="L").save(folder / first)
    (folder / second).unlink()
    Image.new("L", (8, 8), 128).save(folder / first.split("/")[0] / "stray.png")
    problems = corpus.verify(folder)
    assert any(p.startswith(f"{first}: sha256 mismatch") for p in problems), problems
    assert any(p.startswith(f"{second}: listed in the manifest but missing") for p in problems), problems
    assert any(p == f"{first.split('/')[0]}/stray.png: file not in the manifest" for p in problems), problems
    assert len(problems) == 3


def test_verify_rejects_reserved_sources_disallowed_licences_and_duplicates(tmp_path, manifest):
    folder = _small_corpus(tmp_path, manifest, n=2)
    data = json.loads((folder / "manifest.json").read_text())
    data["files"][0] = {**data["files"][0], "source": "deb:lomiri-wallpapers", "licence": "CC-BY-NC-4.0"}
    data["files"].append(dict(data["files"][1]))
    (folder / "manifest.json").write_text(json.dumps(data))
    problems = corpus.verify(folder)
    name0, name1 = data["files"][0]["file"], data["files"][1]["file"]
    assert any(p.startswith(f"{name0}: source 'deb:lomiri-wallpapers' is reserved") for p in problems), problems
    assert f"{name0}: licence 'CC-BY-NC-4.0' is not in the allowed set" in problems
    assert f"{name1}: listed twice in the manifest" in problems
    entry = {**data["files"][1], "source": "deb:ukui-wallpapers", "original_path": "usr/share/backgrounds/horse.jpg"}
    assert any("held-out/example-scene original" in p for p in corpus._entry_problems(entry))


def test_processing_turns_rgb_into_the_expected_luma_png(tmp_path):
    # a uniform colour: luma 0.299*200 + 0.587*100 + 0.114*50 = 124.2 -> 124 everywhere, short side to SHORT_SIDE
    src = tmp_path / "flat.png"
    Image.new("RGB", (64, 48), (200, 100, 50)).save(src)
    out = corpus.process(src)
    s = corpus.SHORT_SIDE
    assert out.mode == "L" and out.size == (round(64 * s / 48), s)
    assert np.all(np.asarray(out) == 124)
    # two halves, black | white, 2.5:1 -> centre-cropped to 16:9 (71 x 40), dark on the left, light on the right
    halves = np.zeros((40, 100, 3), dtype=np.uint8)
    halves[:, 50:] = 255
    Image.fromarray(halves).save(tmp_path / "halves.png")
    assert corpus.crop_box(100, 40) == (14, 0, 85, 40)
    wide = np.asarray(corpus.process(tmp_path / "halves.png"))
    assert wide.shape == (s, round(71 * s / 40)) and wide[:, :10].max() == 0 and wide[:, -10:].min() == 255
    # EXIF orientation 6 (rotate 90 degrees) is applied before anything else
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.new("RGB", (64, 48), (10, 200, 30)).save(tmp_path / "rot.jpg", exif=exif, quality=95)
    assert corpus.process(tmp_path / "rot.jpg").size == (s, round(64 * s / 48))
    # the PNG: 8-bit grayscale, no metadata chunks
    data = corpus.png_bytes(out)
    assert Image.open(io.BytesIO(data)).mode == "L"
    assert not any(chunk in data for chunk in (b"tEXt", b"iTXt", b"zTXt", b"eXIf", b"iCCP"))
