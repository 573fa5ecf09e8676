"""Input validation of ``+experiment=restore``: every file is checked before any work, with exact messages."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from codesign.io.captures import read_counts
from codesign.experiments.restore import input_files, validate
from codesign.errors import ConfigError


def _png(path, arr, mode=None):
    Image.fromarray(arr, mode=mode).save(path) if mode else Image.fromarray(arr).save(path)
    return path


def test_sixteen_bit_png_and_tiff_are_read_as_counts(tmp_path):
    import tifffile

    arr = (np.arange(64 * 64).reshape(64, 64) * 2).astype(np.uint16)
    assert np.array_equal(read_counts(_png(tmp_path / "a.png", arr)), arr.astype(np.float64))
    tifffile.imwrite(tmp_path / "a.tif", arr)
    assert np.array_equal(read_counts(tmp_path / "a.tif"), arr.astype(np.float64))


def test_eight_bit_and_colour_inputs_are_refused(tmp_path):
    with pytest.raises(ConfigError, match="has uint8 samples: expected 16-bit sensor counts"):
        read_counts(_png(tmp_path / "g8.png", np.zeros((8, 8), np.uint8)))
    with pytest.raises(ConfigError, match="PNG mode RGB: expected a single-channel 16-bit image"):
        read_counts(_png(tmp_path / "rgb.png", np.zeros((8, 8, 3), np.uint8)))


def test_size_and_range_are_checked_against_the_sensor(tmp_path):
    ok = _png(tmp_path / "ok.png", np.full((64, 64), 100, np.uint16))
    small = _png(tmp_path / "small.png", np.full((32, 64), 100, np.uint16))
    hot = _png(tmp_path / "hot.png", np.full((64, 64), 60000, np.uint16))
    assert len(validate([ok], 64, 65535.0)) == 1
    with pytest.raises(ConfigError, match=r"small.png' ?: is 64 x 32 px: the checkpoint's network resolution is "
                                          r"64 x 64 \(data.image_size\)"):
        validate([ok, small], 64, 65535.0)
    with pytest.raises(ConfigError, match="has counts up to 60000 DN, above the sensor's 4095 DN"):
        validate([hot], 64, 4095.0)


def test_input_paths(tmp_path):
    with pytest.raises(ConfigError, match="input = None: give a 16-bit PNG/TIFF sensor image"):
        input_files(None)
    with pytest.raises(ConfigError, match="no such file or folder"):
        input_files(tmp_path / "missing.png")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(ConfigError, match="folder holds no .png, .tif, .tiff files"):
        input_files(tmp_path)
    with pytest.raises(ConfigError, match="must be a .png, .tif, .tiff file"):
        input_files(tmp_path / "notes.txt")
    _png(tmp_path / "b.png", np.zeros((4, 4), np.uint16))
    _png(tmp_path / "a.png", np.zeros((4, 4), np.uint16))
    assert [p.name for p in input_files(tmp_path)] == ["a.png", "b.png"]


def test_a_network_of_any_size_restores_a_non_square_capture_at_the_bin_asked_in_tiles(tmp_path):
    """+experiment=restore with a conditioned network (model=wiener_naf, fresh: its classical start): a 230 x 150
    capture, larger than the training crops and not square, binned 4 x 4 (restore.bin=4), decoded in 32 px tiles: a
    57 x 37 restoration whose uniform scene comes back at its level."""
    import torch
    from omegaconf import OmegaConf

    from codesign import api
    from codesign.io.captures import save_png16
    from codesign.sensor.spec import SensorSpec
    from codesign.train.checkpoint import save_checkpoint
    from codesign.train.model_setup import build_model
    from tests.train._util import tiny_cfg

    cfg = tiny_cfg("model=wiener_naf")
    torch.manual_seed(0)
    state = {"model": build_model(cfg).state_dict(), "step": 1, "config": OmegaConf.to_container(cfg, resolve=True)}
    ck = save_checkpoint(tmp_path / "checkpoint.pt", state)
    sensor = SensorSpec()
    level = 0.3 * sensor.gain_dn_per_e * sensor.full_well_e
    capture = tmp_path / "frame.png"
    save_png16(capture, np.full((230, 150), level / 65535.0), scale=65535.0)
    out = api.restore(capture, ck, "restore.bin=4", "restore.tile=32", "logging.tensorboard=false",
                      run_dir=tmp_path / "restore")
    restored = read_counts(out["run_dir"] / "restored_frame.png") / 65535.0
    assert restored.shape == (57, 37) and out["bin"] == 4.0
    assert out["captures"][0]["tile"] == 32 and out["captures"][0]["output_size"] == [57, 37]
    assert np.abs(restored - 0.3).max() < 1e-4


def test_restore_bin_is_refused_when_it_leaves_too_few_pixels(tmp_path):
    from codesign.experiments.restore import working_bin
    from codesign.models.capture import RestoreSpec
    from omegaconf import OmegaConf

    cfg = OmegaConf.create({"sensor": {"resolution": 2532}, "data": {"image_size": 96, "scales": [96, 256]}})
    images = [np.zeros((100, 60))]
    assert working_bin(RestoreSpec(bin=2.0), cfg, images) == 2.0
    with pytest.raises(ConfigError, match=r"^restore\.bin = 9\.8906: leaves the smallest capture \(60 px a side\) "
                       r"under 8 network pixels: at most 7\.5 sensor pixels per network pixel$"):
        working_bin(RestoreSpec(), cfg, images)
