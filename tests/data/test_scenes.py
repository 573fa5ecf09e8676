"""Scene loading (formats, scaling, skipping), the fixed split, random / fixed crops, built-in scenes, config."""
from __future__ import annotations

import socket
import warnings
from pathlib import Path

import numpy as np
import pytest
import tifffile
import torch
from omegaconf import OmegaConf
from PIL import Image

from codesign.data import (PROCEDURAL_SCENES, DataConfig, ParamConfig, SceneLoadWarning, SceneSampler,
                           SceneSource, UnreadableImage, build_scene_sampler, build_scene_source,
                           builtin_scene_names, load_image, procedural_scene, split_scene_names)
from codesign.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
LUMA = np.array([0.299, 0.587, 0.114])


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    """Seven good images of every supported kind, one corrupt PNG and a text file (in a sub-folder too)."""
    d = tmp_path / "scenes"
    (d / "sub").mkdir(parents=True)
    g8 = np.zeros((40, 48), np.uint8)
    g8[0, 0], g8[0, 1] = 255, 100
    Image.fromarray(g8).save(d / "gray8.png")
    g16 = np.zeros((40, 48), np.uint16)
    g16[0, 0], g16[0, 1] = 65535, 1000
    Image.fromarray(g16).save(d / "sub" / "gray16.png")
    Image.fromarray(np.full((32, 32, 3), (200, 100, 50), np.uint8)).save(d / "rgb.jpg", quality=100)
    tifffile.imwrite(d / "sub" / "gray16.tif", g16)
    tifffile.imwrite(d / "rgb16.tiff", np.stack([g16, g16 // 2, g16 // 4], -1), photometric="rgb")
    rgba = np.zeros((24, 24, 4), np.uint8)
    rgba[..., 0], rgba[..., 1], rgba[..., 2], rgba[..., 3] = 10, 20, 30, 0  # fully transparent
    Image.fromarray(rgba, "RGBA").save(d / "rgba.png")
    Image.fromarray(np.full((30, 30), 128, np.uint8)).save(d / "Upper.PNG")
    (d / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4)
    (d / "notes.txt").write_text("not an image")
    return d


def _source(folder: Path, **kw) -> SceneSource:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SceneLoadWarning)
        return SceneSource.from_folder(folder, **kw)


def test_values_are_scaled_by_bit_depth_not_by_max(folder):
    g8 = load_image(folder / "gray8.png")
    assert g8.dtype == np.float32 and g8.shape == (40, 48)
    assert g8[0, 0] == 1.0 and g8[0, 1] == pytest.approx(100 / 255) and g8[1, 1] == 0.0
    for name in ("sub/gray16.png", "sub/gray16.tif"):
        g16 = load_image(folder / name)
        assert g16[0, 0] == 1.0 and g16[0, 1] == pytest.approx(1000 / 65535, rel=1e-6), name
    rgb = load_image(folder / "rgb.jpg")
    assert rgb.shape == (32, 32)
    assert rgb.mean() == pytest.approx(LUMA @ [200, 100, 50] / 255, abs=2 / 255)
    # a 16-bit colour TIFF keeps its 16-bit precision (tifffile), luma of (1000, 500, 250) / 65535
    rgb16 = load_image(folder / "rgb16.tiff")
    assert rgb16[0, 1] == pytest.approx(LUMA @ [1000, 500, 250] / 65535, rel=1e-5)
    assert rgb16[0, 0] == pytest.approx(LUMA @ [65535, 32767, 16383] / 65535, rel=1e-6)
    rgba = load_image(folder / "rgba.png")  # alpha dropped, not multiplied in
    assert rgba.mean() == pytest.approx(LUMA @ [10, 20, 30] / 255, rel=1e-6)
    with pytest.raises(UnreadableImage):
        load_image(folder / "corrupt.png")


def test_folder_source_skips_the_corrupt_file_with_one_warning(folder):
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        src = SceneSource.from_folder(folder)
    ours = [w for w in rec if issubclass(w.category, SceneLoadWarning)]
    assert len(ours) == 1
    msg = str(ours[0].message)
    assert "skipped 1 " in msg and "corrupt.png" in msg and "data.folder" in msg
    assert src.names == ["Upper.PNG", "gray8.png", "rgb.jpg", "rgb16.tiff", "rgba.png", "sub/gray16.png",
                         "sub/gray16.tif"]


@pytest.mark.parametrize("make", ["missing", "empty", "junk_only"])
def test_folder_without_images_raises_naming_data_folder(tmp_path, make):
    d = tmp_path / "x"
    if make != "missing":
        d.mkdir()
    if make == "junk_only":
        (d / "a.png").write_bytes(b"garbage")
        (d / "b.txt").write_text("text")
    with pytest.raises(ConfigError) as e, warnings.catch_warnings():
        warnings.simplefilter("ignore", SceneLoadWarning)
        build_scene_source({"scenes": "folder", "folder": str(d)})
    assert e.value.key == "data.folder" and str(d) in str(e.value)


def test_split_is_fixed_disjoint_and_complete():
    names = [f"img_{i:03d}.png" for i in range(50)]
    train, test = split_scene_names(names, 0.1, seed=0)
    assert len(test) == 5 and len(train) == 45
    assert not set(train) & set(test) and set(train) | set(test) == set(names)
    assert (train, test) == split_scene_names(names, 0.1, seed=0)
    rev_train, rev_test = split_scene_names(names[::-1], 0.1, seed=0)  # independent of the listing order
    assert set(rev_test) == set(test)
    assert set(split_scene_names(names, 0.1, seed=1)[1]) != set(test)
    assert len(split_scene_names(names[:2], 0.1, 0)[1]) == 1  # at least one test image from two
    assert split_scene_names(names[:1], 0.1, 0) == (names[:1], [])


def test_folder_split_and_builtin_split(folder):
    a, b = _source(folder, split_seed=3), _source(folder, split_seed=3)
    assert a.split_names("test") == b.split_names("test") and len(a.split_names("test")) == 1
    assert sorted(a.split_names("train") + a.split_names("test")) == sorted(a.names)
    src = build_scene_source({"scenes": "builtin"})
    train, test = src.split_names("train"), src.split_names("test")
    assert test and not set(train) & set(test)
    assert not set(PROCEDURAL_SCENES) & set(train + test)  # charts are reached by name only


def test_sampler_batches_shape_range_and_determinism(folder):
    src = _source(folder)
    s1 = SceneSampler(src, "train", 16, 6, _gen(5))
    s2 = SceneSampler(_source(folder), "train", 16, 6, _gen(5))
    s3 = SceneSampler(src, "train", 16, 6, _gen(6))
    b1, b2, b3 = next(s1), next(s2), next(s3)
    assert b1.shape == (6, 1, 16, 16) and b1.dtype == torch.float32
    assert b1.min() >= 0 and b1.max() <= 1
    assert torch.equal(b1, b2) and torch.equal(next(s1), next(s2)) and s1.last_names == s2.last_names
    assert not torch.equal(b1, b3)
    assert set(s1.last_names) <= set(src.split_names("train"))


def test_flips(tmp_path):
    d = tmp_path / "one"
    d.mkdir()
    ramp = (np.arange(16 * 16).reshape(16, 16) * 200).astype(np.uint16)  # every pixel distinct
    Image.fromarray(ramp).save(d / "ramp.png")
    img = torch.from_numpy(ramp.astype(np.float32) / 65535)
    variants = {"id": img, "v": img.flip(0), "h": img.flip(1), "vh": img.flip([0, 1])}
    seen = set()
    for crop in SceneSampler(SceneSource.from_folder(d), "train", 16, 32, _gen(0)).sample():
        seen |= {k for k, v in variants.items() if torch.allclose(crop[0], v)}
    assert seen == set(variants)
    no_flip = SceneSampler(SceneSource.from_folder(d), "train", 16, 8, _gen(0), flips=False).sample()
    assert all(torch.allclose(c[0], img) for c in no_flip)
    with pytest.raises(ConfigError) as e:  # one image: no test split
        SceneSampler(SceneSource.from_folder(d), "test", 16, 2, _gen(0))
    assert e.value.key == "data.folder"


def test_small_images_are_upscaled_to_fit_the_crop(tmp_path):
    d = tmp_path / "small"
    d.mkdir()
    checker = ((np.indices((20, 40)).sum(0) % 2) * 255).astype(np.uint8)
    Image.fromarray(checker).save(d / "checker.png")
    src = SceneSource.from_folder(d)
    up = src.image("checker.png", 64)
    assert up.shape == (64, 128) and up.min() >= 0 and up.max() <= 1  # bicubic overshoot clamped
    assert up.mean().item() == pytest.approx(0.5, abs=0.05)
    assert src.image("checker.png").shape == (20, 40)  # the original is kept too
    batch = SceneSampler(src, "train", 64, 3, _gen(1)).sample()
    assert batch.shape == (3, 1, 64, 64) and batch.min() >= 0 and batch.max() <= 1


def test_fixed_batch_is_centre_crops_without_flips(folder):
    src = _source(folder)
    s = SceneSampler(src, "train", 8, 4, _gen(0))
    fb = s.fixed_batch(["gray8.png", 0])
    assert fb.shape == (2, 1, 8, 8) and fb.dtype == torch.float32
    full = torch.from_numpy(load_image(folder / "gray8.png"))  # 40 x 48 -> rows 16:24, cols 20:28
    assert torch.equal(fb[0, 0], full[16:24, 20:28])
    assert torch.equal(fb, s.fixed_batch(["gray8.png", 0]))
    assert torch.equal(fb[1], src.fixed_batch([src.split_names("train")[0]], 8)[0])
    with pytest.raises(ConfigError):
        s.fixed_batch(["nope.png"])


def test_file_failing_at_decode_time_is_dropped(tmp_path):
    d = tmp_path / "trunc"
    d.mkdir()
    Image.fromarray(np.full((16, 16), 60, np.uint8)).save(d / "good.png")
    noise = np.random.default_rng(0).integers(0, 255, (64, 64), dtype=np.uint8)
    Image.fromarray(noise).save(d / "bad.jpg")
    raw = (d / "bad.jpg").read_bytes()
    (d / "bad.jpg").write_bytes(raw[: len(raw) // 3])  # header intact, data truncated
    src = SceneSource.from_folder(d, test_fraction=0.5)
    assert set(src.names) == {"good.png", "bad.jpg"}
    s = SceneSampler(src, "all", 8, 4, _gen(0))
    with pytest.warns(SceneLoadWarning, match="bad.jpg"):
        for _ in range(3):
            batch = s.sample()
    assert s.last_names == ["good.png"] * 4 and torch.allclose(batch, torch.tensor(60 / 255))
    assert src.split_names("all") == ["good.png"]


def test_builtin_scenes_load_without_network(monkeypatch):
    def no_network(*args, **kwargs):
        raise OSError("network disabled in this test")

    monkeypatch.setattr(socket.socket, "connect", no_network)
    monkeypatch.setattr(socket, "create_connection", no_network)
    names = builtin_scene_names()
    photos = [n for n in names if n not in PROCEDURAL_SCENES]
    assert len(photos) >= 5 and {"camera", "astronaut", "coffee", "moon"} <= set(photos)
    assert names[-len(PROCEDURAL_SCENES):] == list(PROCEDURAL_SCENES)
    src = SceneSource.builtin(cache_mb=0)
    assert src.names == names
    for n in names:
        img = src.image(n)
        assert img.dim() == 2 and img.dtype == torch.float32 and min(img.shape) >= 150, n
        assert 0 <= img.min() and img.max() <= 1 and img.std() > 0.01 or n == "uniform", n
    assert src.image("camera").max() == 1.0  # 8-bit 255 -> 1.0
    batch = SceneSampler(src, "train", 64, 4, _gen(0)).sample()
    assert batch.shape == (4, 1, 64, 64)


@pytest.mark.parametrize("size", [1, 7, 64, 101])
def test_procedural_scenes_any_size(size):
    for name in PROCEDURAL_SCENES:
        img = procedural_scene(name, size)
        assert img.shape == (size, size) and img.dtype == torch.float32, name
        assert img.min() >= 0 and img.max() <= 1, name
    if size >= 64:
        assert procedural_scene("siemens_star", size).mean().item() == pytest.approx(0.5, abs=0.02)
        assert procedural_scene("checkerboard", size).unique().tolist() == [0.0, 1.0]
        pts = procedural_scene("point_grid", size)
        assert pts.sum().item() == ((size - 1) // (size // 8) + 1) ** 2
    assert torch.all(procedural_scene("uniform", size) == 0.5)
    with pytest.raises(ConfigError):
        procedural_scene("spiral", size)


def test_default_node_and_config_validation(folder):
    from hydra.core.config_store import ConfigStore

    cfg = OmegaConf.create(ConfigStore.instance().load("data/default.yaml").node)  # the config option data=default
    dc = DataConfig.from_config(cfg)
    assert isinstance(dc, DataConfig) and dc.params == ParamConfig()
    assert (dc.scenes, dc.image_size, dc.padded_size, dc.batch_size) == ("builtin", 256, 384, 8)
    assert (dc.test_fraction, dc.split_seed, dc.folder) == (0.1, 0, None)
    assert DataConfig.from_config(OmegaConf.create({"data": cfg})) == dc  # a root config works too
    with pytest.warns(SceneLoadWarning):
        s = build_scene_sampler(OmegaConf.merge(cfg, {"scenes": "folder", "folder": str(folder), "batch_size": 2}),
                                "test", _gen(0), crop_size=8)
    assert s.batch_size == 2 and not s.flips and s.source.config.folder == folder
    with pytest.warns(SceneLoadWarning):
        src = build_scene_source({**OmegaConf.to_container(cfg), "scenes": "folder", "folder": str(folder)})
    assert len(src) == 7


@pytest.mark.parametrize("key, value", [
    ("scenes", "imagenet"), ("folder", None), ("image_size", 0), ("image_size", 12.5), ("padded_size", 128),
    ("batch_size", 0), ("test_fraction", 0.0), ("test_fraction", 1.0), ("split_seed", -1), ("flips", "yes"),
    ("cache_mb", -1), ("params", {"c2_range": [2, 1]}),
])
def test_bad_data_config_names_the_key(key, value):
    cfg = {"scenes": "folder" if key == "folder" else "builtin", "image_size": 256, "padded_size": 384,
           key: value}
    with pytest.raises(ConfigError) as e:
        build_scene_source(cfg)
    expected = "data.params.c2_range" if key == "params" else f"data.{key}"
    assert e.value.key == expected and expected in str(e.value)
