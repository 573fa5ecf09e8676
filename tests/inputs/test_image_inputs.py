"""Image files a user hands over: captures for +experiment=restore (corrupt, truncated, wrong size, wrong bit
depth, wrong sample type) and scene folders (data.folder). Each is a ConfigError naming the file and what is
wrong, raised before any restoration starts. The basic cases (8-bit, RGB, size, range, paths) are in
tests/experiments/test_restore.py."""
from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import tifffile
import torch
from omegaconf import OmegaConf
from PIL import Image

from codesign.data.images import SceneLoadWarning
from codesign.data.scenes import build_scene_source
from codesign.train.checkpoint import save_checkpoint
from codesign.io.captures import read_counts
from codesign.experiments.restore import input_files, validate
from codesign.train.model_setup import build_model
from codesign.errors import ConfigError
from tests.train._util import tiny_cfg
from tests.inputs._run import config_error

N = 16


def _png16(path, value=1000, shape=(N, N)):
    Image.fromarray(np.full(shape, value, np.uint16)).save(path)
    return path


def _noise(shape=(64, 64)) -> np.ndarray:
    # incompressible samples: half of the file then cuts into the pixel data, not into the header
    return np.random.default_rng(0).integers(0, 65535, shape, dtype=np.uint16)


def _truncated(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def _make(tmp_path, kind):
    """One bad capture file of the given kind."""
    if kind == "truncated_png":
        Image.fromarray(_noise()).save(tmp_path / "a.png")
        return _truncated(tmp_path / "a.png")
    if kind == "empty_png":
        (tmp_path / "a.png").write_bytes(b"")
    elif kind == "text_png":
        (tmp_path / "a.png").write_text("not an image")
    elif kind == "truncated_tif":
        tifffile.imwrite(tmp_path / "a.tif", _noise())
        return _truncated(tmp_path / "a.tif")
    elif kind == "float_tif":
        tifffile.imwrite(tmp_path / "a.tif", np.zeros((N, N), np.float32))
    elif kind == "int32_tif":
        tifffile.imwrite(tmp_path / "a.tif", np.zeros((N, N), np.int32))
    elif kind == "rgb16_tif":
        tifffile.imwrite(tmp_path / "a.tif", np.zeros((N, N, 3), np.uint16))
    elif kind == "bilevel_png":
        Image.fromarray(np.ones((N, N), bool)).save(tmp_path / "a.png")
    return next(tmp_path.glob("a.*"))


@pytest.mark.parametrize("kind,message", [
    ("truncated_png", r"cannot be read \(OSError: image file is truncated"),
    ("empty_png", r"cannot be read \(UnidentifiedImageError: cannot identify image file"),
    ("text_png", r"cannot be read \(UnidentifiedImageError: cannot identify image file"),
    ("truncated_tif", r"cannot be read \(ValueError: failed to read \d+ bytes, got \d+\)$"),
    ("float_tif", r"has float32 samples: expected 16-bit sensor counts \(unsigned 16-bit integers, as "
                  r"\+experiment=simulate writes them\)$"),
    ("int32_tif", r"has int32 samples: expected 16-bit sensor counts \(unsigned 16-bit integers, as "
                  r"\+experiment=simulate writes them\)$"),
    ("rgb16_tif", r"has shape \(16, 16, 3\): expected one channel \(H, W\)$"),
    ("bilevel_png", r"PNG mode 1: expected a single-channel 16-bit image \(mode I;16\)$"),
])
def test_corrupt_or_wrong_type_capture_names_the_file(tmp_path, kind, message):
    path = _make(tmp_path, kind)
    with pytest.raises(ConfigError, match="^input = " + re.escape(repr(str(path))) + ": " + message):
        validate([path], N, 65535.0)


def test_wrong_bit_depth_counts_above_the_sensor_full_scale(tmp_path):
    # a 16-bit capture from a 12-bit sensor holds at most 4095 DN; 5000 means another sensor (or scaled data)
    path = _png16(tmp_path / "a.png", value=5000)
    with pytest.raises(ConfigError, match=r"^input = .*a.png': has counts up to 5000 DN, above the sensor's 4095 DN "
                                          r"\(sensor.bit_depth\)$"):
        validate([path], N, 4095.0)


def test_every_file_is_checked_before_the_first_is_used(tmp_path):
    good = [_png16(tmp_path / f"{i}.png") for i in range(3)]
    bad = _png16(tmp_path / "z.png", shape=(N, N + 1))
    with pytest.raises(ConfigError, match=r"z.png': is 17 x 16 px: the checkpoint's network resolution is 16 x 16"):
        validate(good + [bad], N, 65535.0)


def test_two_files_that_would_write_one_output(tmp_path):
    _png16(tmp_path / "cap.png")
    tifffile.imwrite(tmp_path / "cap.tif", np.zeros((N, N), np.uint16))
    with pytest.raises(ConfigError, match=r"holds files that would write the same output restored_cap.png: rename "
                                          r"one of \['cap.png', 'cap.tif'\]$"):
        input_files(tmp_path)


def test_sixteen_bit_counts_are_read_exactly(tmp_path):
    arr = np.arange(N * N, dtype=np.uint16).reshape(N, N) * 200
    Image.fromarray(arr).save(tmp_path / "a.png")
    assert np.array_equal(read_counts(tmp_path / "a.png"), arr)


def test_restore_refuses_a_bad_capture_before_any_restoration(tmp_path, monkeypatch, capsys):
    cfg = tiny_cfg()
    torch.manual_seed(0)
    state = {"model": build_model(cfg).state_dict(), "step": 1, "config": OmegaConf.to_container(cfg, resolve=True)}
    ck = save_checkpoint(tmp_path / "checkpoint.pt", state)
    capture = _png16(tmp_path / "capture.png", shape=(32, 32))  # the checkpoint's network works at 48 x 48
    line = config_error(monkeypatch, capsys, tmp_path / "run", "+experiment=restore", f"checkpoint={ck}",
                        f"input={capture}")
    assert line == (f"codesign: configuration error: input = '{capture}': is 32 x 32 px: the checkpoint's network "
                    f"resolution is 48 x 48 (data.image_size); simulate captures at that size with "
                    f"+experiment=simulate data.image_size=48 data.padded_size=64; a network that takes any size "
                    f"restores any capture (checkpoint=pretrained)")


# ---- scene folders (data.folder) ---------------------------------------------------------------------------
def _folder_error(folder) -> str:
    with pytest.raises(ConfigError) as info, warnings.catch_warnings():
        warnings.simplefilter("ignore", SceneLoadWarning)
        build_scene_source({"scenes": "folder", "folder": str(folder)})
    return str(info.value)


def test_a_folder_without_the_folder_source_is_refused_not_ignored(tmp_path):
    """data.folder=DIR alone used to train on the built-in scenes without a word."""
    _png16(tmp_path / "one.png")
    with pytest.raises(ConfigError) as info:
        build_scene_source({"scenes": "builtin", "folder": str(tmp_path)})
    assert str(info.value) == (f"data.folder = '{tmp_path}': is only read with data.scenes=folder (data.scenes is "
                               f"builtin): add data.scenes=folder to train on this folder, or leave data.folder null")


def test_scene_folder_that_does_not_exist_or_is_a_file(tmp_path):
    assert _folder_error(tmp_path / "nope") == (f"data.folder = '{tmp_path / 'nope'}': must be an existing folder "
                                                f"of PNG/JPEG/TIFF images")
    _png16(tmp_path / "one.png")
    assert _folder_error(tmp_path / "one.png").endswith("must be an existing folder of PNG/JPEG/TIFF images")


def test_scene_folder_of_corrupt_images_only(tmp_path):
    (tmp_path / "a.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    Image.fromarray(_noise()).save(tmp_path / "b.png")
    _truncated(tmp_path / "b.png")
    (tmp_path / "notes.txt").write_text("not an image, not counted")
    assert _folder_error(tmp_path) == (f"data.folder = '{tmp_path}': must hold at least one readable "
                                       f".png/.jpg/.jpeg/.tif/.tiff image (searched recursively; found 2 image "
                                       f"file(s), 2 unreadable)")


def test_corrupt_scene_files_are_skipped_with_a_warning_naming_them(tmp_path):
    _png16(tmp_path / "good.png", shape=(32, 32))
    _png16(tmp_path / "good2.png", shape=(32, 32))
    (tmp_path / "bad.png").write_bytes(b"garbage")
    with pytest.warns(SceneLoadWarning, match=r"data.folder: skipped 1 unreadable image file\(s\) under .*: bad.png"):
        src = build_scene_source({"scenes": "folder", "folder": str(tmp_path)})
    assert sorted(src.names) == ["good.png", "good2.png"]


def test_scenes_smaller_than_the_crop_are_counted_in_one_warning(tmp_path):
    """A 1 x 1 and a 40 x 40 image among larger ones used to be upscaled to the crop without a word."""
    from codesign.data.scenes import build_scene_sampler

    _png16(tmp_path / "tiny.png", shape=(1, 1))
    _png16(tmp_path / "small.png", shape=(40, 40))
    for i in range(3):
        _png16(tmp_path / f"big{i}.png", shape=(80, 96))
    cfg = {"scenes": "folder", "folder": str(tmp_path), "image_size": 64, "padded_size": 64, "batch_size": 2}
    with pytest.warns(SceneLoadWarning) as caught:
        sampler = build_scene_sampler(cfg, "all", torch.Generator().manual_seed(0))
    messages = [str(w.message) for w in caught if issubclass(w.category, SceneLoadWarning)]
    assert messages == ["data.folder: 2 of 5 scene(s) of the 'all' split are smaller than the 64-pixel crop (the "
                        "smallest: tiny.png, 1 x 1); they are upscaled (antialiased bicubic), which blurs them"]
    assert sampler.sample().shape == (2, 1, 64, 64)
    for name in ("tiny.png", "small.png"):
        (tmp_path / name).unlink()
    with warnings.catch_warnings():
        warnings.simplefilter("error", SceneLoadWarning)  # no small scene: no warning
        build_scene_sampler(cfg, "all", torch.Generator())


@pytest.mark.parametrize("head", [b"II*\x00", b"MM\x00*"], ids=["little-endian", "big-endian"])
def test_a_tiff_header_over_garbage_cannot_be_read_as_a_tiff(tmp_path, head):
    # random bytes behind a TIFF's magic number: tifffile finds no page and returns an empty array, which was
    # described as "has shape (0,): expected one channel (H, W)"
    path = tmp_path / "a.tif"
    path.write_bytes(head + np.random.default_rng(0).bytes(4096))
    with pytest.raises(ConfigError, match="^input = " + re.escape(repr(str(path))) + r": cannot be read as a TIFF "
                                          r"\(no image in it: .*\): expected a single-channel 16-bit PNG or TIFF$"):
        read_counts(path)


@pytest.mark.parametrize("dtype", [np.int8, np.uint8])
def test_an_8_bit_npy_psf_is_refused_as_an_8_bit_png_is(tmp_path, dtype):
    # an 8-bit PNG is refused (it cannot hold a PSF's range); the same samples saved as .npy were taken
    from codesign.optics import OpticsSpec
    from codesign.optics.measured import load_measured

    frame = np.zeros((64, 64), dtype)
    frame[30:34, 30:34] = 100
    path = tmp_path / "psf.npy"
    np.save(path, frame)
    spec = OpticsSpec.with_samples_across(192, focal_n=160).replace(psf_file=str(path), psf_pitch_m=5.4e-6)
    with pytest.raises(ConfigError, match="^optics.psf_file = " + re.escape(repr(str(path))) +
                       f": has {np.dtype(dtype).name} samples: 8-bit integers cannot hold a PSF's range"):
        load_measured(spec)
