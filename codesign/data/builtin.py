"""Scenes that need no download: photographs shipped inside the scikit-image wheel, and procedural charts.

The scikit-image files are read straight from the installed package folder with our own loader (same luma and
bit-depth scaling as user folders); ``skimage.data`` functions are not called because several of them fetch
from the network through pooch. Only files that are part of the wheel are listed (checked offline for
scikit-image 0.26: cells3d, eagle, kidney, lily, skin, ... need a download and are left out).
"""
from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import torch

from codesign.errors import ConfigError, require_number

__all__ = ["SKIMAGE_SCENES", "PROCEDURAL_SCENES", "skimage_data_dir", "available_skimage_scenes",
           "builtin_scene_names", "procedural_scene"]

# name -> file under skimage/data. Natural / textured grayscale-convertible photographs only: synthetic
# charts (chessboard, color wheel, phantom, logo), the tiny 102 px microaneurysms crop, the horse silhouette
# and the duplicate 'cat' (= chelsea) are left out.
SKIMAGE_SCENES: dict[str, str] = {
    "astronaut": "astronaut.png",
    "brick": "brick.png",
    "camera": "camera.png",
    "cell": "cell.png",
    "chelsea": "chelsea.png",
    "clock": "clock_motion.png",
    "coffee": "coffee.png",
    "coins": "coins.png",
    "grass": "grass.png",
    "gravel": "gravel.png",
    "hubble_deep_field": "hubble_deep_field.jpg",
    "immunohistochemistry": "ihc.png",
    "moon": "moon.png",
    "motorcycle": "motorcycle_left.png",
    "page": "page.png",
    "retina": "retina.jpg",
    "rocket": "rocket.jpg",
    "text": "text.png",
}

PROCEDURAL_SCENES: tuple[str, ...] = ("siemens_star", "checkerboard", "uniform", "point_grid")
PROCEDURAL_DEFAULT_SIZE = 512  # pixels, when no crop size asks for another


def skimage_data_dir() -> Path | None:
    """The ``skimage/data`` folder of the installed scikit-image, found without importing it; None if absent."""
    spec = importlib.util.find_spec("skimage")
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0]) / "data"


def available_skimage_scenes() -> dict[str, Path]:
    """name -> file path of the SKIMAGE_SCENES present on disk (a trimmed install may lack some)."""
    d = skimage_data_dir()
    if d is None:
        return {}
    return {name: d / f for name, f in SKIMAGE_SCENES.items() if (d / f).is_file()}


def builtin_scene_names() -> list[str]:
    """All built-in scene names: the available scikit-image photographs, then the procedural charts."""
    return [*available_skimage_scenes(), *PROCEDURAL_SCENES]


def procedural_scene(name: str, size: int) -> torch.Tensor:
    """A synthetic (size, size) float32 scene in [0, 1], for optics checks.

    siemens_star: 36 black/white sector pairs around the centre, edges antialiased with a one-pixel linear
        ramp (the spokes merge into mid-gray where they are narrower than a pixel, as a real chart would);
    checkerboard: 8 x 8 squares of 0 and 1 (square side size // 8, at least 1 pixel);
    uniform: a flat field of 0.5 (PSF / flare tests without scene structure);
    point_grid: single pixels of 1.0 on a black field, spaced max(4, size // 8) and centred (PSF probes).
    """
    if name not in PROCEDURAL_SCENES:
        raise ConfigError("scene", name, f"must be one of {', '.join(PROCEDURAL_SCENES)}")
    n = require_number("size", size, lo=1, integer=True)
    c = (n - 1) / 2.0
    coords = torch.arange(n, dtype=torch.float64) - c
    if name == "uniform":
        return torch.full((n, n), 0.5, dtype=torch.float32)
    if name == "checkerboard":
        side = max(1, n // 8)
        idx = torch.arange(n) // side
        return ((idx[:, None] + idx[None, :]) % 2).to(torch.float32)
    if name == "point_grid":
        step = max(4, n // 8)
        img = torch.zeros(n, n, dtype=torch.float32)
        count = (n - 1) // step + 1
        first = (n - 1 - (count - 1) * step) // 2  # centre the grid of points
        img[first::step, first::step] = 1.0
        return img
    # siemens_star
    y, x = coords[:, None], coords[None, :]
    r, theta = torch.hypot(x, y), torch.atan2(y, x)
    cycles = 36
    period = 2 * math.pi / cycles  # one black + one white sector
    phase = torch.remainder(theta, period) / period  # [0, 1): first half white, second half black
    edge = torch.minimum(phase, 1 - phase).clone()  # distance to the 0 / 1 edge, in periods
    to_mid = (phase - 0.5).abs()  # distance to the mid-period edge
    dist_px = torch.minimum(edge, to_mid) * period * r  # arc length to the nearest edge, pixels
    white = phase < 0.5
    sign = torch.where(white, 1.0, -1.0).to(torch.float64)
    return (0.5 + sign * dist_px).clamp(0.0, 1.0).to(torch.float32)
