"""A set of scenes (image files or built-in ones) with a fixed train/test split and a decoded-image cache.

Images are tensors of shape (H, W), float32 radiance in [0, 1]. Files are decoded lazily (a photo collection
can be far larger than memory) and kept in a least-recently-used cache bounded in megabytes.
"""
from __future__ import annotations

import hashlib
import math
import warnings
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import torch
import torch.nn.functional as F

from codesign.data.builtin import (
    PROCEDURAL_DEFAULT_SIZE,
    PROCEDURAL_SCENES,
    available_skimage_scenes,
    procedural_scene,
)
from codesign.data.images import (
    SceneLoadWarning,
    UnreadableImage,
    find_image_files,
    load_image,
    probe_image,
)
from codesign.errors import ConfigError, require_choice, require_number

__all__ = ["SceneEntry", "SceneSource", "split_scene_names", "upscale_to_fit", "centre_crop", "SPLITS"]

SPLITS = ("train", "test", "all")
_WARN_NAMES = 5  # how many skipped files a warning names


@dataclass(frozen=True)
class SceneEntry:
    """One scene: ``name`` is the path relative to the folder (posix) or the built-in name."""

    name: str
    path: Path | None  # None for procedural scenes
    procedural: bool = False
    size: tuple[int, int] | None = None  # (H, W) from the file's header (folders), None when not probed


def split_scene_names(names: Sequence[str], test_fraction: float, seed: int) -> tuple[list[str], list[str]]:
    """Deterministic (train, test) split of ``names``, each list in the input order.

    Names are ranked by SHA-256 of "seed, name" and the first round(test_fraction * n) (at least 1 and at most
    n - 1 when n >= 2) form the test set. Hashing the name, not shuffling with a RNG, keeps the split fixed
    across machines and torch versions, and adding or removing files moves few others across the boundary.
    A single scene goes to train (the test set is then empty).
    """
    n = len(names)
    if n < 2:
        return list(names), []
    n_test = min(n - 1, max(1, math.floor(test_fraction * n + 0.5)))
    ranked = sorted(names, key=lambda s: hashlib.sha256(f"{seed}\x00{s}".encode()).hexdigest())
    test = set(ranked[:n_test])
    return [s for s in names if s not in test], [s for s in names if s in test]


def upscale_to_fit(img: torch.Tensor, size: int) -> torch.Tensor:
    """(H, W) -> (H', W') with min(H', W') = size when the shorter side is below ``size``; else unchanged.

    Antialiased bicubic (aspect ratio kept); bicubic overshoots at edges, so the result is clamped to [0, 1].
    """
    h, w = img.shape
    if min(h, w) >= size:
        return img
    s = size / min(h, w)
    new = (size, max(size, round(w * s))) if h <= w else (max(size, round(h * s)), size)
    out = F.interpolate(img[None, None], size=new, mode="bicubic", align_corners=False, antialias=True)
    return out[0, 0].clamp_(0.0, 1.0)


def centre_crop(img: torch.Tensor, size: int) -> torch.Tensor:
    """The central ``size`` x ``size`` pixels of an (H, W) image."""
    h, w = img.shape
    top, left = (h - size) // 2, (w - size) // 2
    return img[top:top + size, left:left + size]


class SceneSource:
    """Scenes with a fixed train/test split. Build with ``from_folder``, ``builtin`` or build_scene_source.

    names: every scene; split_names('train' | 'test' | 'all'): the natural scenes of a split (procedural
    charts of the built-in set are in no split: they are for optics checks, not image statistics, and are
    reached by name). ``image(name, min_size)`` returns the decoded (H, W) float32 image in [0, 1].
    """

    def __init__(self, entries: Iterable[SceneEntry], *, test_fraction: float = 0.1, split_seed: int = 0,
                 cache_mb: float = 1024.0, origin: str = "", key: str = "data.folder"):
        self.entries = {e.name: e for e in entries}
        self.origin, self.key = origin, key  # key: the config key that errors about this source name
        self.config = None  # the DataConfig when built by build_scene_source
        self.test_fraction = require_number("data.test_fraction", test_fraction, lo=0, hi=1, lo_open=True,
                                            hi_open=True)
        self.split_seed = require_number("data.split_seed", split_seed, lo=0, integer=True)
        self.cache_bytes = int(require_number("data.cache_mb", cache_mb, lo=0) * 2**20)
        natural = [e.name for e in self.entries.values() if not e.procedural]
        train, test = split_scene_names(natural, self.test_fraction, self.split_seed)
        self._splits = {"train": train, "test": test, "all": natural}
        self._cache: OrderedDict[tuple[str, int], torch.Tensor] = OrderedDict()
        self._cached_bytes = 0

    # -- construction -------------------------------------------------------------------------------------
    @classmethod
    def from_folder(cls, folder: str | Path, **kwargs) -> "SceneSource":
        """Every readable PNG/JPEG/TIFF under ``folder`` (recursive). Unreadable files are skipped with one
        SceneLoadWarning; a missing folder, or one without a usable image, raises ConfigError(data.folder)."""
        folder = Path(folder).expanduser()
        if not folder.is_dir():
            raise ConfigError("data.folder", str(folder), "must be an existing folder of PNG/JPEG/TIFF images")
        files, bad = find_image_files(folder), []
        entries = []
        for p in files:
            try:
                size = probe_image(p)
            except UnreadableImage:
                bad.append(p.relative_to(folder).as_posix())
                continue
            entries.append(SceneEntry(p.relative_to(folder).as_posix(), p, size=tuple(size)))
        if bad:
            shown = ", ".join(bad[:_WARN_NAMES]) + (", ..." if len(bad) > _WARN_NAMES else "")
            warnings.warn(f"data.folder: skipped {len(bad)} unreadable image file(s) under {folder}: {shown}",
                          SceneLoadWarning, stacklevel=2)
        if not entries:
            raise ConfigError("data.folder", str(folder),
                              f"must hold at least one readable .png/.jpg/.jpeg/.tif/.tiff image (searched "
                              f"recursively; found {len(files)} image file(s), {len(bad)} unreadable)")
        return cls(entries, origin=str(folder), **kwargs)

    @classmethod
    def builtin(cls, **kwargs) -> "SceneSource":
        """The scikit-image photographs shipped in its wheel plus the procedural charts (no network)."""
        photos = available_skimage_scenes()
        if not photos:
            raise ConfigError("data.scenes", "builtin",
                              "needs scikit-image's bundled images (pip install scikit-image), or use "
                              "data.scenes=folder with data.folder=PATH")
        entries = [SceneEntry(n, p) for n, p in photos.items()]
        entries += [SceneEntry(n, None, procedural=True) for n in PROCEDURAL_SCENES]
        return cls(entries, origin="builtin", key="data.scenes", **kwargs)

    # -- queries -----------------------------------------------------------------------------------------
    @property
    def names(self) -> list[str]:
        """Every scene's name, in the source's order."""
        return list(self.entries)

    def __len__(self) -> int:
        return len(self.entries)

    def smaller_than(self, split: str, size: int) -> list[tuple[str, tuple[int, int]]]:
        """(name, (H, W)) of the probed scenes of ``split`` whose shorter side is below ``size`` (upscaled when
        cropped at that size)."""
        return [(n, self.entries[n].size) for n in self.split_names(split)
                if self.entries[n].size is not None and min(self.entries[n].size) < size]

    def split_names(self, split: str) -> list[str]:
        """Names of the scenes of ``split`` ('train', 'test' or 'all'), files that failed to decode removed."""
        return list(self._splits[require_choice("split", split, SPLITS)])

    def image(self, name: str, min_size: int | None = None) -> torch.Tensor:
        """The (H, W) float32 image in [0, 1]; upscaled (antialiased bicubic) so that min(H, W) >= min_size.

        Procedural scenes are generated at exactly ``min_size`` (or 512) pixels. A file that fails to decode
        is dropped from every split with a SceneLoadWarning and UnreadableImage is raised.
        """
        if name not in self.entries:
            raise ConfigError("scene", name, f"is not in this source ({self.origin}); see SceneSource.names")
        entry = self.entries[name]
        size = 0 if min_size is None else require_number("crop_size", min_size, lo=1, integer=True)
        if entry.procedural:
            return self._cached((name, size or PROCEDURAL_DEFAULT_SIZE),
                                lambda: procedural_scene(name, size or PROCEDURAL_DEFAULT_SIZE))
        base = self._cached((name, 0), lambda: self._decode(entry))
        if size and min(base.shape) < size:  # small image: keep the upscaled copy too, keyed by the size
            return self._cached((name, size), lambda: upscale_to_fit(base, size))
        return base

    def fixed_batch(self, items: Sequence[str | int], crop_size: int, split: str = "all") -> torch.Tensor:
        """(N, 1, crop, crop) centre crops (no flips) of the named scenes, or of indices into ``split``."""
        crop = require_number("crop_size", crop_size, lo=1, integer=True)
        pool = self.split_names(split)
        out = []
        for it in items:
            if isinstance(it, int) and not isinstance(it, bool):
                if not -len(pool) <= it < len(pool):
                    raise ConfigError("scene index", it, f"must be in [0, {len(pool)}) for split '{split}'")
                it = pool[it]
            out.append(centre_crop(self.image(it, crop), crop))
        if not out:
            raise ConfigError("scenes", list(items), "must name at least one scene")
        return torch.stack(out)[:, None].contiguous()

    # -- internals ---------------------------------------------------------------------------------------
    def _decode(self, entry: SceneEntry) -> torch.Tensor:
        try:
            return torch.from_numpy(load_image(entry.path))
        except UnreadableImage as e:
            for names in self._splits.values():
                if entry.name in names:
                    names.remove(entry.name)
            warnings.warn(f"{self.key}: skipped unreadable image {entry.name} ({e})", SceneLoadWarning,
                          stacklevel=3)
            raise

    def _cached(self, key: tuple[str, int], make) -> torch.Tensor:
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        img = make()
        nbytes = img.numel() * img.element_size()
        if nbytes <= self.cache_bytes:
            self._cache[key] = img
            self._cached_bytes += nbytes
            while self._cached_bytes > self.cache_bytes:  # evict the least recently used
                _, old = self._cache.popitem(last=False)
                self._cached_bytes -= old.numel() * old.element_size()
        return img
