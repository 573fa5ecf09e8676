"""A plate's files for a fabrication shop: heights in metres (.npy, float64), a 16-bit PNG and a 16-bit TIFF whose
metadata hold the scale (height = count x metres_per_count), and the JSON sidecar describing the plate. Every file
is written atomically (a temp file, then renamed)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from codesign.io.files import atomic_write_bytes

FULL_SCALE = 65535


def height_counts(height: np.ndarray, metres_per_count: float) -> np.ndarray:
    """Heights as 16-bit counts: round(h / metres_per_count), clipped to 0..65535."""
    return np.clip(np.rint(height / metres_per_count), 0, FULL_SCALE).astype(np.uint16)


def write_height_png(path: Path, height: np.ndarray, metres_per_count: float, meta: dict) -> None:
    """16-bit grayscale PNG; the sidecar's fields (``meta``) as JSON in its ``codesign`` text chunk and the scale
    in its ``metres_per_count`` chunk."""
    from PIL import Image
    from PIL.PngImagePlugin import PngInfo

    info = PngInfo()
    info.add_text("metres_per_count", repr(float(metres_per_count)))
    info.add_text("codesign", json.dumps(meta))
    img = Image.fromarray(height_counts(height, metres_per_count))
    atomic_write_bytes(path, lambda fh: img.save(fh, format="PNG", pnginfo=info))


def write_height_tiff(path: Path, height: np.ndarray, metres_per_count: float, pitch_m: float, meta: dict) -> None:
    """16-bit TIFF: the sidecar's fields as JSON in ImageDescription, the pixel pitch as its resolution
    (pixels per centimetre)."""
    import tifffile

    per_cm = 1e-2 / pitch_m
    atomic_write_bytes(path, lambda fh: tifffile.imwrite(
        fh, height_counts(height, metres_per_count), description=json.dumps(meta),
        resolution=(per_cm, per_cm), resolutionunit="CENTIMETER", metadata=None))


def read_height_png(path: Path) -> tuple[np.ndarray, float, dict]:
    """(heights [m], metres_per_count, sidecar fields) of a PNG written by ``write_height_png``."""
    from PIL import Image

    with Image.open(path) as img:
        counts = np.array(img).astype(np.float64)
        scale = float(img.text["metres_per_count"])
        meta = json.loads(img.text["codesign"])
    return counts * scale, scale, meta


def read_height_tiff(path: Path) -> tuple[np.ndarray, dict]:
    """(heights [m], sidecar fields) of a TIFF written by ``write_height_tiff``."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        meta = json.loads(page.description)
        counts = page.asarray().astype(np.float64)
    return counts * meta["metres_per_count"], meta
