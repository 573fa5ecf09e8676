"""The last findings of the issue-59 audit: misleading messages and silent inputs (one test per case, each fast,
in-process)."""
from __future__ import annotations

import os

import numpy as np
import pytest

from codesign.errors import ConfigError, require_number, require_numbers
from codesign.experiments.restore import input_files
from codesign.optics.masks.records import load_record
from codesign.train.checkpoint import load_checkpoint
from tests.inputs._run import config_error, fresh_run_folder_state  # noqa: F401 - the fixture, for every test


@pytest.fixture
def fifo(tmp_path):
    """A named pipe: opening it would block until a writer comes, so no check may open it."""
    path = tmp_path / "pipe"
    os.mkfifo(path)
    return path


@pytest.mark.parametrize("device", ["/dev/null", "/dev/zero"])
def test_checkpoint_device_is_named_a_device(device):
    with pytest.raises(ConfigError) as err:
        load_checkpoint(device)
    assert "a character device, not a regular file" in str(err.value) and "no such" not in str(err.value)


def test_checkpoint_fifo_is_named_a_pipe(fifo):
    with pytest.raises(ConfigError) as err:
        load_checkpoint(fifo, key="init.checkpoint")
    message = str(err.value)
    assert message.startswith("init.checkpoint = ") and "a named pipe (FIFO), not a regular file" in message


def test_restore_input_device_and_fifo(fifo):
    for path, kind in (("/dev/zero", "a character device"), (str(fifo), "a named pipe (FIFO)")):
        with pytest.raises(ConfigError) as err:
            input_files(path)
        assert str(err.value).startswith("input = ") and f"is {kind}, not a regular file" in str(err.value)


def test_mask_init_fifo(fifo):
    with pytest.raises(ConfigError) as err:
        load_record(str(fifo), "mask.init", "must be a mask record")
    assert "a named pipe (FIFO), not a regular file" in str(err.value)


def test_sensor_resolution_zero_names_sensor_resolution(tmp_path, monkeypatch, capsys):
    line = config_error(monkeypatch, capsys, tmp_path / "run", "+experiment=simulate", "debug=smoke",
                        "sensor.resolution=0")
    assert line.endswith("sensor.resolution = 0: must be an integer >= 8 and <= 65536"), line


@pytest.mark.parametrize("call", ["restore_image", "checkpoint_config"])
def test_api_checkpoint_none_says_what_is_allowed(call):
    import codesign

    args = (np.full((96, 96), 500.0),) if call == "restore_image" else ()
    with pytest.raises(ConfigError) as err:
        getattr(codesign, call)(*args, checkpoint=None)
    assert str(err.value) == f"{call} checkpoint = None: must be 'pretrained' or a checkpoint.pt path (a str or " \
        "os.PathLike)"


@pytest.mark.parametrize("value", [np.float32(1e6), np.float64(3.5), np.int64(7), np.array(2.0), np.uint16(9)])
def test_numpy_scalars_are_numbers(value):
    assert require_number("k", value, lo=0, hi=1e12) == float(value)
    assert require_numbers("k", np.array([value, value]), "a list") == [float(value)] * 2


@pytest.mark.parametrize("value", [np.bool_(True), True, np.array([1.0]), np.float32("nan"), np.complex64(1)])
def test_numpy_bools_arrays_and_nonfinite_stay_refused(value):
    with pytest.raises(ConfigError):
        require_number("k", value)


def test_sensor_image_takes_a_numpy_alpha():
    from codesign.api_checks import check_alpha

    assert check_alpha("sensor_image alpha_l", np.float32(1e6)) == 1e6


def _resume_with_init(monkeypatch, caplog, tmp_path, typed, started):
    """resume_if_possible on a run folder holding a checkpoint whose run started from ``started``, this run typed
    init.checkpoint=``typed``; the loading itself stubbed (the warning is what is tested); the warnings logged."""
    import logging
    from types import SimpleNamespace

    from omegaconf import OmegaConf

    from codesign.experiments import resume

    saved = {"trainer": {"steps": 4}, "init": {"checkpoint": started}}
    monkeypatch.setattr(resume, "load_checkpoint", lambda path, key: {"config": saved})
    for name in ("check_trained", "check_resume_config", "resume_trainer"):
        monkeypatch.setattr(resume, name, lambda *a, **k: None)
    (tmp_path / "checkpoint.pt").write_bytes(b"")
    cfg = OmegaConf.create({"trainer": {"steps": 4, "resume": None}, "init": {"checkpoint": typed}})
    with caplog.at_level(logging.WARNING, logger="codesign.train"):
        resume.resume_if_possible(SimpleNamespace(step=5), cfg, tmp_path)
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


def test_resume_says_a_typed_init_checkpoint_is_not_used(monkeypatch, caplog, tmp_path):
    lines = _resume_with_init(monkeypatch, caplog, tmp_path, "/other/checkpoint.pt", None)
    assert len(lines) == 1 and lines[0].startswith("init.checkpoint = '/other/checkpoint.pt': not used: the run "
                                                   "resumed from") and "(step 5)" in lines[0], lines


@pytest.mark.parametrize("typed, started", [(None, None), ("auto", "auto"), ("/a.pt", "/a.pt")])
def test_resume_quiet_when_init_checkpoint_is_the_runs_own(monkeypatch, caplog, tmp_path, typed, started):
    assert _resume_with_init(monkeypatch, caplog, tmp_path, typed, started) == []


def test_restore_warns_of_a_saturated_capture(tmp_path, caplog):
    import logging

    from codesign.experiments.restore import validate
    from codesign.io.captures import save_png16

    full, half = tmp_path / "full.png", tmp_path / "half.png"
    save_png16(full, np.full((16, 16), 65535.0))
    save_png16(half, np.where(np.arange(256).reshape(16, 16) < 128, 65535.0, 100.0))  # 50 %: not over the line
    with caplog.at_level(logging.WARNING, logger="codesign.restore"):
        validate([full, half], None, 65535.0)
    lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(lines) == 1 and lines[0].startswith(f"input = {str(full)!r}: 100.0 % of its pixels are at the "
                                                   "sensor's full scale (65535 DN)"), lines


def test_api_warns_of_a_saturated_capture():
    import torch

    from codesign.api_checks import check_capture_fits

    with pytest.warns(UserWarning, match=r"^restore_image counts: 100\.0 % of its pixels are at the sensor's full "):
        check_capture_fits("restore_image counts", torch.full((16, 16), 4095.0), 1, 4095.0)


def test_api_psf_and_lsr_refuses_what_the_command_line_refuses():
    import codesign

    with pytest.raises(ConfigError, match=r"^mask\.levels = 1: must be an integer >= 2"):
        codesign.psf_and_lsr(cfg=codesign.compose("debug=smoke", "mask.levels=1"))


def test_api_build_camera_refuses_a_padded_size_that_wraps():
    import codesign

    with pytest.raises(ConfigError, match=r"^data\.padded_size = 50: must be >= data\.image_size \+ PSF kernel - 1"):
        codesign.build_camera(codesign.compose("debug=smoke", "data.image_size=48", "data.padded_size=50"))
