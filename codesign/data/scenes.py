"""Scene batches for training and evaluation, and building them from the ``data`` config.

A batch is a (B, 1, crop, crop) float32 tensor of scene radiance in [0, 1] on the CPU (the caller moves it to
its device): random crops with random flips for training, centre crops for evaluation.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping, Sequence

import torch

from codesign.config.keys import unknown_keys
from codesign.config.store import register, spec_node
from codesign.data.builtin import builtin_scene_names
from codesign.data.images import SceneLoadWarning, UnreadableImage
from codesign.data.paramconfig import ParamConfig
from codesign.data.source import SceneSource
from codesign.errors import ConfigError, require_choice, require_list, require_number

__all__ = ["SceneSampler", "DataConfig", "build_scene_source", "build_scene_sampler",
           "SceneSource", "builtin_scene_names", "heldout_source", "HELDOUT_DIR"]


class SceneSampler:
    """Endless random scene crops from one split of a SceneSource; deterministic for a given generator state.

    Each batch: B scenes drawn uniformly with replacement, each upscaled first if its shorter side is below
    ``crop_size`` (antialiased bicubic), a uniformly placed crop_size x crop_size window, then (flips=True)
    independent horizontal and vertical flips with probability 1/2. Random draws, in order: scene indices
    (B,), flips (B, 2), crop corners (B, 2) as fractions of the free range. ``last_names`` holds the scenes of
    the last batch (of its part, when ``sample`` was given one).
    """

    def __init__(self, source: SceneSource, split: str, crop_size: int, batch_size: int,
                 generator: torch.Generator, flips: bool = True):
        self.source = source
        self.split = require_choice("split", split, ("train", "test", "all"))
        self.crop_size = require_number("crop_size", crop_size, lo=1, integer=True)
        self.batch_size = require_number("batch_size", batch_size, lo=1, integer=True)
        if not isinstance(generator, torch.Generator) or generator.device.type != "cpu":
            raise TypeError(f"generator must be a CPU torch.Generator, got {generator!r}")
        self.generator, self.flips = generator, bool(flips)
        self.last_names: list[str] = []
        pool = self._pool()  # fail now, not at the first batch, when the split is empty
        small = source.smaller_than(self.split, self.crop_size)
        if small:  # upscaling blurs them: said once, with the count, not silently
            name, (h, w) = min(small, key=lambda item: min(item[1]))
            warnings.warn(f"{source.key}: {len(small)} of {len(pool)} scene(s) of the '{self.split}' split are "
                          f"smaller than the {self.crop_size}-pixel crop (the smallest: {name}, {h} x {w}); they "
                          f"are upscaled (antialiased bicubic), which blurs them", SceneLoadWarning, stacklevel=2)

    def _pool(self) -> list[str]:
        pool = self.source.split_names(self.split)
        if not pool:
            n = len(self.source.split_names("all"))
            raise ConfigError(self.source.key, self.source.origin,
                              f"has {n} usable scene(s), none in the '{self.split}' split (a test split needs "
                              f">= 2 scenes; see data.test_fraction)")
        return pool

    def __iter__(self) -> "SceneSampler":
        return self

    def __next__(self) -> torch.Tensor:
        return self.sample()

    def _draw_image(self, pool: list[str], index: int, crop: int) -> tuple[str, torch.Tensor]:
        """The image of ``pool[index]`` (at least ``crop`` px a side); if it fails to decode (then dropped from the split), the next scene of
        the split takes its place (no random draw, so the ranks of a distributed run stay in step)."""
        name = pool[index]
        while True:
            try:
                return name, self.source.image(name, crop)
            except UnreadableImage:
                current = self._pool()
                name = current[index % len(current)]

    def sample(self, part: slice | None = None, crop_size: int | None = None) -> torch.Tensor:
        """One (B, 1, crop, crop) float32 batch in [0, 1]; with ``part`` only those samples of it; ``crop_size``:
        this batch's crop instead of the sampler's (a pool camera at another pixel scale needs another).

        The random choices of all B samples are drawn whichever part is asked for (B scalars each), so the
        generator advances identically on every rank of a distributed run and the parts of the ranks together
        are the batch one process would draw (torch's DistributedSampler splits one shared sequence the same way).
        """
        g, b = self.generator, self.batch_size
        c = self.crop_size if crop_size is None else crop_size
        pool = self._pool()
        idx = torch.randint(len(pool), (b,), generator=g).tolist()
        flip = (torch.rand(b, 2, generator=g) < 0.5).tolist()
        # crop corners as fractions of the free range: drawn without knowing the image sizes, so the other
        # ranks' samples never need decoding
        corner = torch.rand(b, 2, generator=g, dtype=torch.float64).tolist()
        mine = range(b)[part] if part is not None else range(b)
        out = torch.empty(len(mine), 1, c, c, dtype=torch.float32)
        self.last_names = []
        for j, i in enumerate(mine):
            name, img = self._draw_image(pool, idx[i], c)
            h, w = img.shape
            top = min(int(corner[i][0] * (h - c + 1)), h - c)
            left = min(int(corner[i][1] * (w - c + 1)), w - c)
            crop = img[top:top + c, left:left + c]
            dims = [d for d, f in zip((0, 1), flip[i]) if f and self.flips]  # (vertical, horizontal)
            out[j, 0] = crop.flip(dims) if dims else crop
            self.last_names.append(name)
        return out

    def fixed_batch(self, items: Sequence[str | int], crop_size: int | None = None) -> torch.Tensor:
        """(N, 1, crop, crop) centre crops, no flips: names of any scene of the source, or indices into this
        sampler's split (evaluation; the same scenes every call)."""
        return self.source.fixed_batch(items, self.crop_size if crop_size is None else crop_size, self.split)


@dataclass(frozen=True)
class DataConfig:
    """The validated ``data`` block; its field defaults are the config's (codesign/config/store.py). Sizes in px.

    scenes: builtin (photographs shipped inside scikit-image + procedural charts: no download) | folder (every
    PNG/JPEG/TIFF under ``folder``, recursive; 8/16 bit; colour -> luma); folder: the image folder when scenes is
    folder (relative to the launch directory); image_size: network image side (simulated captures are downsampled
    to it, and the default crop size); padded_size: network input side after zero padding (>= image_size);
    batch_size: the global batch; test_fraction: share of the scenes held out for testing, in (0, 1) (>= 1 test
    scene when >= 2 scenes); split_seed: seed of the fixed train/test split (hash of seed and relative path);
    flips: random horizontal / vertical flips of training crops; cache_mb: decoded-image cache, MiB (least recently
    used images are evicted); params: the Sec. 6.2 scene-parameter distribution (ParamConfig).
    masks: train a restorer over a pool of masks (a list of 'published', 'defocus:R', 'random:FAMILY[:N]' or
    mask-record paths; null = the configured mask alone; codesign/train/mask_pool.py); mask_every: steps per pool
    member; mask_draws: random draws around each listed mask; mask_jitter: their spread, times each mask's RMS
    parameter value; mask_lsr: [lo, hi] sampled-LSR range of the 'random:FAMILY' members.
    scales: train over pixel scales (with data.masks): a list of S, the whole sensor binned to S px per side (the
    same sensor pitch, data.image_size px of it cropped); null = data.image_size alone.
    """

    scenes: str = "builtin"
    folder: Path | None = None
    image_size: int = 256
    padded_size: int = 384
    batch_size: int = 8
    test_fraction: float = 0.1
    split_seed: int = 0
    flips: bool = True
    cache_mb: float = 1024.0
    params: ParamConfig = field(default_factory=ParamConfig)
    masks: tuple | None = None
    mask_every: int = 4
    mask_draws: int = 0
    mask_jitter: float = 0.1
    mask_lsr: tuple = (1e-4, 1e-2)
    scales: tuple | None = None

    @classmethod
    def from_config(cls, cfg: Mapping | Any) -> DataConfig:
        """Validate the ``data`` config node (or a root config holding one); errors name the ``data.*`` key."""
        if cfg is not None and "data" in cfg and "scenes" not in cfg:
            cfg = cfg["data"]
        if cfg is None or not hasattr(cfg, "get"):
            raise ConfigError("data", cfg, "must be a mapping of the data.* keys (codesign/data/scenes.py: "
                              "DataConfig)")
        unknown_keys("data", cfg, DATA_KEYS)
        d = cls  # the defaults of keys a mapping leaves out
        scenes = require_choice("data.scenes", cfg.get("scenes", d.scenes), ("builtin", "folder"))
        folder = cfg.get("folder")
        if scenes == "folder":
            if not isinstance(folder, (str, Path)) or not str(folder).strip():
                raise ConfigError("data.folder", folder, "must be the path of an image folder when "
                                  "data.scenes=folder")
            folder = Path(str(folder)).expanduser()
        elif folder is not None:  # a folder the built-in source would silently ignore
            raise ConfigError("data.folder", folder, "is only read with data.scenes=folder (data.scenes is builtin): "
                              "add data.scenes=folder to train on this folder, or leave data.folder null")
        # the sensor model's bounds (SensorSpec), checked here under the keys the user types
        image_size = require_number("data.image_size", cfg.get("image_size", d.image_size), lo=8, hi=65536,
                                    integer=True)
        padded = cfg.get("padded_size", d.padded_size)
        padded_size = require_number("data.padded_size", padded, lo=8, hi=65536, integer=True)
        if padded_size < image_size:
            raise ConfigError("data.padded_size", padded, f"must be an integer >= data.image_size ({image_size})")
        flips = cfg.get("flips", d.flips)
        if not isinstance(flips, bool):
            raise ConfigError("data.flips", flips, "must be true or false")
        return cls(
            scenes=scenes, folder=Path(folder).expanduser() if scenes == "folder" else None,
            image_size=image_size, padded_size=padded_size,
            batch_size=require_number("data.batch_size", cfg.get("batch_size", d.batch_size), lo=1, integer=True),
            test_fraction=require_number("data.test_fraction", cfg.get("test_fraction", d.test_fraction), lo=0, hi=1,
                                         lo_open=True, hi_open=True),
            split_seed=require_number("data.split_seed", cfg.get("split_seed", d.split_seed), lo=0, integer=True),
            flips=flips,
            cache_mb=require_number("data.cache_mb", cfg.get("cache_mb", d.cache_mb), lo=0),
            params=ParamConfig.from_config(cfg.get("params")),
            masks=_masks(cfg.get("masks")),
            mask_every=require_number("data.mask_every", cfg.get("mask_every", d.mask_every), lo=1, integer=True),
            mask_draws=require_number("data.mask_draws", cfg.get("mask_draws", d.mask_draws), lo=0, hi=1000,
                                      integer=True),
            mask_jitter=require_number("data.mask_jitter", cfg.get("mask_jitter", d.mask_jitter), lo=0, hi=10),
            mask_lsr=_lsr_range(cfg.get("mask_lsr", d.mask_lsr)),
            scales=_scales(cfg.get("scales")),
        )


DATA_KEYS = tuple(f.name for f in fields(DataConfig))
MASKS_ALLOWED = ("must be a list of masks, each 'published', 'defocus:R' (R in rad, 0 < R <= 200), 'random:FAMILY' or "
                 "'random:FAMILY:N' (N random masks of a family) or the path of a mask record (best_mask.json, "
                 "learned_mask.json), or null for the configured mask alone")
SCALES_ALLOWED = "must be a non-empty list of integer pixel scales in [8, sensor.resolution], or null"


def _masks(value) -> tuple | None:
    """data.masks as a tuple of its members (each member checked where the pool is built:
    codesign/train/mask_pool.py), or None."""
    if value is None:
        return None
    items = require_list("data.masks", value, MASKS_ALLOWED)
    if not items:
        raise ConfigError("data.masks", items, MASKS_ALLOWED.replace("a list", "a non-empty list"))
    return tuple(items)


def _scales(value) -> tuple | None:
    """data.scales as a sorted tuple of distinct integers >= 8 (the sensor's resolution bounds them where the pool
    is built), or None."""
    if value is None:
        return None
    items = require_list("data.scales", value, SCALES_ALLOWED)
    if not items:
        raise ConfigError("data.scales", items, SCALES_ALLOWED)
    scales = [require_number(f"data.scales[{i}]", v, lo=8, hi=65536, integer=True) for i, v in enumerate(items)]
    if len(set(scales)) != len(scales):
        raise ConfigError("data.scales", items, SCALES_ALLOWED + " (each scale once)")
    return tuple(sorted(scales))


def _lsr_range(value) -> tuple:
    allowed = "must be [lo, hi] with 0 < lo < hi <= 1 (the sampled LSR of the random pool members)"
    items = require_list("data.mask_lsr", value, allowed)
    if len(items) != 2:
        raise ConfigError("data.mask_lsr", items, allowed)
    lo, hi = (require_number(f"data.mask_lsr[{i}]", v, lo=0, lo_open=True, hi=1) for i, v in enumerate(items))
    if not lo < hi:
        raise ConfigError("data.mask_lsr", items, allowed)
    return (float(lo), float(hi))


def build_scene_source(cfg: Mapping | DataConfig) -> SceneSource:
    """The SceneSource of the ``data`` config (validated first); ``source.config`` holds the DataConfig."""
    dc = cfg if isinstance(cfg, DataConfig) else DataConfig.from_config(cfg)
    kw = dict(test_fraction=dc.test_fraction, split_seed=dc.split_seed, cache_mb=dc.cache_mb)
    source = SceneSource.from_folder(dc.folder, **kw) if dc.scenes == "folder" else SceneSource.builtin(**kw)
    source.config = dc
    return source


HELDOUT_DIR = Path(__file__).resolve().parent / "heldout"


def heldout_source() -> SceneSource:
    """The photographs shipped for evaluation only (codesign/data/heldout/, sources and licences in its
    SOURCES.md): 16 grayscale 512 x 512 scenes that no training, tuning or design step reads; split 'all'."""
    if not HELDOUT_DIR.is_dir():
        raise ConfigError("evaluate.scenes", "heldout", f"needs the held-out photographs at {HELDOUT_DIR}, which "
                          "this installation lacks (reinstall codesign, or set evaluate.scenes=data)")
    return SceneSource.from_folder(HELDOUT_DIR)


def build_scene_sampler(cfg: Mapping | DataConfig, split: str, generator: torch.Generator,
                        crop_size: int | None = None, source: SceneSource | None = None) -> SceneSampler:
    """A SceneSampler over ``split`` with data.batch_size and data.flips (flips only for 'train');
    crop_size defaults to data.image_size. Pass ``source`` to share one source (and its cache)."""
    dc = cfg if isinstance(cfg, DataConfig) else DataConfig.from_config(cfg)
    source = source if source is not None else build_scene_source(dc)
    crop = dc.image_size if crop_size is None else crop_size
    return SceneSampler(source, split, crop, dc.batch_size, generator, flips=dc.flips and split == "train")


register("data", "default", spec_node(DataConfig))
