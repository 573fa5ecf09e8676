"""Reading image files as monochromatic scene radiance: float32 (H, W) arrays in [0, 1].

Scaling is by the file's nominal bit depth (8 bit / 255, 16 bit / 65535), never by the image maximum, so the
relative brightness of scenes is kept. Colour is reduced to luma Y = 0.299 R + 0.587 G + 0.114 B (the paper
converts its colour photographs to grayscale radiance); an alpha channel is dropped.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

__all__ = ["IMAGE_SUFFIXES", "SceneLoadWarning", "UnreadableImage", "find_image_files", "load_image",
           "probe_image", "to_luma"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
_TIFF = (".tif", ".tiff")
_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float64)


class SceneLoadWarning(UserWarning):
    """Some image files could not be read and were skipped."""


class UnreadableImage(Exception):
    """An image file that neither Pillow nor tifffile can decode into a 2-D radiance map."""


def find_image_files(folder: Path) -> list[Path]:
    """Every PNG/JPEG/TIFF file under ``folder`` (recursive), sorted by relative path.

    Hidden files and folders (names starting with '.') are ignored: they are editor / OS artefacts (e.g.
    macOS '._x.png' resource forks), not scenes. Symlinked folders are not followed (no cycles).
    """
    found = []
    for root, dirs, files in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in files:
            if not name.startswith(".") and name.lower().endswith(IMAGE_SUFFIXES):
                found.append(Path(root) / name)
    return sorted(found, key=lambda p: p.relative_to(folder).as_posix())


def to_luma(arr: np.ndarray, full_scale: float) -> np.ndarray:
    """(H, W) or (H, W, C) samples with nominal maximum ``full_scale`` -> float32 (H, W) in [0, 1].

    C = 2 (gray + alpha) keeps channel 0; C >= 3 takes the luma of the first three (alpha dropped).
    Float data (full_scale None) is taken as radiance already and clipped to [0, 1].
    """
    a = np.asarray(arr)
    if a.dtype == bool:
        a, full_scale = a.astype(np.float64), 1.0
    a = a.astype(np.float64)
    if a.ndim == 3:
        if a.shape[-1] >= 3:
            a = a[..., :3] @ _LUMA
        elif a.shape[-1] in (1, 2):
            a = a[..., 0]
    if a.ndim != 2 or min(a.shape) < 1:
        raise UnreadableImage(f"not a 2-D image (shape {np.shape(arr)})")
    if full_scale is not None:
        a = a / full_scale
    if not np.isfinite(a).all():
        raise UnreadableImage("non-finite samples")
    return np.clip(a, 0.0, 1.0).astype(np.float32)


def _tiff_bits(img) -> int:
    """Largest BitsPerSample (tag 258) of a Pillow TIFF image; 8 when absent."""
    bits = getattr(img, "tag_v2", {}).get(258, 8)
    return max(bits) if isinstance(bits, (tuple, list)) else int(bits)


def _load_pillow(path: Path) -> np.ndarray:
    from PIL import Image, ImageOps

    with Image.open(path) as img:
        if path.suffix.lower() in _TIFF and _tiff_bits(img) > 8 and img.mode in ("RGB", "RGBA", "L", "LA"):
            # Pillow reduces 16-bit colour TIFFs to 8-bit samples; tifffile keeps the full precision.
            raise UnreadableImage("high bit depth colour TIFF: use tifffile")
        img.load()
        img = ImageOps.exif_transpose(img)  # camera JPEGs store their orientation in EXIF
        mode = img.mode
        if mode == "1":
            return to_luma(np.asarray(img, dtype=bool), 1.0)
        if mode.startswith("I;16"):
            return to_luma(np.asarray(img), 65535.0)
        if mode == "I":  # 32-bit container: old Pillow's 16-bit PNG; TIFF int32 goes to tifffile
            if path.suffix.lower() in _TIFF:
                raise UnreadableImage("32-bit integer TIFF: use tifffile")
            return to_luma(np.asarray(img), 65535.0)
        if mode == "F":
            return to_luma(np.asarray(img), None)
        if mode in ("P", "PA", "RGBa", "La"):
            img = img.convert("RGBA")
        elif mode not in ("L", "LA", "RGB", "RGBA"):  # CMYK, YCbCr, LAB, HSV
            img = img.convert("RGB")
        return to_luma(np.asarray(img), 255.0)


def _load_tifffile(path: Path) -> np.ndarray:
    import tifffile

    with tifffile.TiffFile(path) as tif:
        a = tif.pages[0].asarray()  # first page / image of a multi-page file
    a = np.squeeze(a)
    if a.ndim == 3 and a.shape[-1] not in (2, 3, 4) and a.shape[0] in (2, 3, 4):
        a = np.moveaxis(a, 0, -1)  # planar (C, H, W) storage
    if a.dtype == bool:
        return to_luma(a, 1.0)
    if np.issubdtype(a.dtype, np.integer):
        return to_luma(a, float(np.iinfo(a.dtype).max))
    return to_luma(a, None)


def load_image(path: str | os.PathLike) -> np.ndarray:
    """Decode one image file into float32 (H, W) radiance in [0, 1]; raises UnreadableImage on failure.

    Pillow first; TIFFs it cannot read, or would read at reduced precision, go to tifffile.
    """
    path = Path(path)
    errors = []
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # e.g. Pillow's "truncated" / EXIF notices: failures raise
            return _load_pillow(path)
    except Exception as e:  # noqa: BLE001 - any decoder failure means 'unreadable'
        errors.append(f"Pillow: {type(e).__name__}: {e}")
    if path.suffix.lower() in _TIFF:
        try:
            return _load_tifffile(path)
        except Exception as e:  # noqa: BLE001
            errors.append(f"tifffile: {type(e).__name__}: {e}")
    raise UnreadableImage(f"{path}: " + "; ".join(errors))


def probe_image(path: Path) -> tuple[int, int]:
    """Cheap validity check without decoding the pixels: returns (height, width) or raises UnreadableImage.

    Reading every pixel of a large photo set at start-up would take minutes, so only the header (and, for PNG,
    the chunk CRCs via verify()) is checked here; a file that fails later, at decode time, is dropped then.
    """
    errors = []
    try:
        from PIL import Image

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(path) as img:
                w, h = img.size
                img.verify()
        if w < 1 or h < 1:
            raise UnreadableImage("empty image")
        return h, w
    except Exception as e:  # noqa: BLE001
        errors.append(f"Pillow: {type(e).__name__}: {e}")
    if path.suffix.lower() in _TIFF:
        try:
            import tifffile

            with tifffile.TiffFile(path) as tif:
                page = tif.pages[0]
                return int(page.imagelength), int(page.imagewidth)
        except Exception as e:  # noqa: BLE001
            errors.append(f"tifffile: {type(e).__name__}: {e}")
    raise UnreadableImage(f"{path}: " + "; ".join(errors))
