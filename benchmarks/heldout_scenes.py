"""How the held-out photographs of codesign/data/heldout/ were made from their originals (run once; kept so that
the processing is on record and can be repeated on the same files).

    python -m benchmarks.heldout_scenes ORIGINALS_DIR codesign/data/heldout

Each original (file names as in codesign/data/heldout/SOURCES.md): EXIF orientation applied; RGB converted to luma
Y = 0.299 R + 0.587 G + 0.114 B in floating point (alpha dropped); centre crop to the largest square; resized to
SIZE x SIZE with Pillow's Lanczos filter on the float image; rounded, clipped to 8 bit and saved as an 8-bit
grayscale PNG (no alpha, no ICC profile) under the short name the table gives.
"""
from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

import numpy as np

SIZE = 512
# short name -> original file name
ORIGINALS = {
    "kingfisher": "bluebird.jpg", "bridge_city": "bridgecity.jpg", "horse": "horse.jpg", "awning": "sky.jpg",
    "sunflower": "sunf.jpg", "canyon_arch": "ashim-d-silva-WeYamle9fDM-unsplash.jpg",
    "mountain_slopes": "cristina-gottardi-wndpWTiDuT0-unsplash.jpg",
    "slot_canyon": "francesco-ungaro-1fzbUyzsHV8-unsplash.jpg", "dunes": "jeremy-bishop-2e3hgvDnCpM-unsplash.jpg",
    "facade": "joshua-coleman-KzPefInJW58-unsplash.jpg", "shore_peak": "luca-micheli-ruWkmt3nU58-unsplash.jpg",
    "snow_ridge": "lucian-dachman-qxO2PBn7eKU-unsplash.jpg", "surf": "luke-stackpoole-mStq-dtsXCQ-unsplash.jpg",
    "jellyfish": "willian-justen-de-vasconcellos-ASKGjAeIY_U-unsplash.jpg",
    "waterfall_bird": "wolfgang-hasselmann-WrVvYxq11Yk-unsplash.jpg",
    "lake_forest": "zetong-li-TbHYpbi_Gbc-unsplash.jpg",
}


def process(src: Path, dst: Path) -> str:
    """Write the processed PNG; returns the original's sha256 (first 16 hex digits)."""
    from PIL import Image, ImageOps

    raw = src.read_bytes()
    img = ImageOps.exif_transpose(Image.open(src)).convert("RGB")
    rgb = np.asarray(img, dtype=np.float64)
    y = 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]
    h, w = y.shape
    s = min(h, w)
    top, left = (h - s) // 2, (w - s) // 2
    square = Image.fromarray(y[top:top + s, left:left + s].astype(np.float32), mode="F")
    small = np.asarray(square.resize((SIZE, SIZE), Image.LANCZOS), dtype=np.float64)
    Image.fromarray(np.clip(np.rint(small), 0, 255).astype(np.uint8), mode="L").save(dst, optimize=True)
    return hashlib.sha256(raw).hexdigest()[:16]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.heldout_scenes", description=__doc__.split("\n\n")[0])
    ap.add_argument("originals", type=Path)
    ap.add_argument("out", type=Path)
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    for name, original in ORIGINALS.items():
        print(f"{name}.png <- {original} (sha256 {process(a.originals / original, a.out / f'{name}.png')})")


if __name__ == "__main__":
    main()
