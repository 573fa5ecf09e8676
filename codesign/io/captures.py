"""16-bit single-channel images: sensor counts in and out (PNG / TIFF)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from codesign.errors import ConfigError
from codesign.io.files import atomic_write_bytes


def save_png16(path: Path, values: np.ndarray, scale: float = 1.0) -> None:
    """``values * scale`` rounded and clipped to 0..65535, written atomically as a 16-bit PNG."""
    from PIL import Image

    arr = np.clip(np.rint(np.asarray(values) * scale), 0, 65535).astype(np.uint16)
    atomic_write_bytes(path, lambda fh: Image.fromarray(arr).save(fh, format="PNG"))


def _read_tiff(path: Path, key: str) -> np.ndarray:
    """The first image of a TIFF file; ConfigError naming ``key`` when the file holds none (a TIFF's magic number
    over other bytes: tifffile then finds no page and returns an empty array, once described as "has shape (0,)")."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        if not len(tif.pages):
            raise ConfigError(key, str(path), "cannot be read as a TIFF (no image in it: its header is a TIFF's, its "
                              "image directory is not): expected a single-channel 16-bit PNG or TIFF")
        return tif.pages[0].asarray()


def read_counts(path: Path, key: str = "input") -> np.ndarray:
    """The raw integer samples of a single-channel 16-bit PNG or TIFF, as float64 counts; ConfigError naming
    ``key`` and the file for anything else."""
    try:
        if path.suffix.lower() in (".tif", ".tiff"):
            arr = _read_tiff(path, key)
        else:
            from PIL import Image

            with Image.open(path) as img:
                mode = img.mode
                arr = np.array(img)
                if mode in ("I;16", "I;16B", "I;16L", "I"):
                    arr = arr.astype(np.uint16) if arr.max(initial=0) < 65536 and arr.min(initial=0) >= 0 else arr
                elif mode != "L":
                    raise ConfigError(key, str(path), f"PNG mode {mode}: expected a single-channel 16-bit "
                                      "image (mode I;16)")
    except ConfigError:
        raise
    except Exception as err:  # noqa: BLE001 - any decoder failure: say which file
        raise ConfigError(key, str(path), f"cannot be read ({type(err).__name__}: {err})") from None
    if arr.ndim != 2:
        raise ConfigError(key, str(path), f"has shape {arr.shape}: expected one channel (H, W)")
    if arr.dtype != np.uint16:
        why = "8-bit files cannot hold the sensor's range" if arr.dtype.itemsize == 1 else \
            "unsigned 16-bit integers, as +experiment=simulate writes them"
        raise ConfigError(key, str(path), f"has {arr.dtype} samples: expected 16-bit sensor counts ({why})")
    return arr.astype(np.float64)


# above this fraction of pixels at full scale a capture is called saturated (a warning, not a refusal: a bright
# but real scene may still restore in its unsaturated part)
SATURATED_WARN = 0.5


def saturation_note(counts, full_scale_dn: float) -> str | None:
    """'N % of its pixels are at the sensor's full scale ...' when more than SATURATED_WARN of ``counts`` (an array
    or tensor of DN) reach ``full_scale_dn``, else None: a fully saturated capture was restored without a word,
    though saturated pixels hold no measurement of the scene."""
    arr = np.asarray(counts.detach().cpu() if hasattr(counts, "detach") else counts)
    fraction = float(np.mean(arr >= full_scale_dn)) if arr.size else 0.0
    if fraction <= SATURATED_WARN:
        return None
    return (f"{100 * fraction:.1f} % of its pixels are at the sensor's full scale ({full_scale_dn:.0f} DN): "
            "saturated pixels hold no measurement of the scene, their restoration is a guess (shorter exposure?)")
