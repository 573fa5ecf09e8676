"""The last findings of the issue-59 audit: misleading messages and silent inputs (one test per case, each fast,
in-process)."""
from __future__ import annotations

import os

import pytest

from codesign.errors import ConfigError
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
    import numpy as np

    import codesign

    args = (np.full((96, 96), 500.0),) if call == "restore_image" else ()
    with pytest.raises(ConfigError) as err:
        getattr(codesign, call)(*args, checkpoint=None)
    assert str(err.value) == f"{call} checkpoint = None: must be 'pretrained' or a checkpoint.pt path (a str or " \
        "os.PathLike)"
