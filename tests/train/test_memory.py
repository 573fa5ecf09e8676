"""Memory bounds before work (issue 16 item 4): a training run estimates what it needs from its sizes, logs it,
and is refused before any work when the machine cannot hold it (it used to start, then die of the OS's
out-of-memory kill with no message)."""
from __future__ import annotations

import re

import pytest

from codesign.train import memory
from tests.inputs._run import config_error
from tests.train._util import tiny_trainer


def test_the_estimate_grows_with_the_batch_and_names_its_parts(tmp_path):
    tr = tiny_trainer(tmp_path)
    one = memory.training_estimate(tr.model, tr.data.camera, 1)
    many = memory.training_estimate(tr.model, tr.data.camera, 100)
    assert set(one) == {"parameters", "activations", "simulation", "base", "total"}  # tiny: no laser halo
    assert one["total"] == sum(v for k, v in one.items() if k != "total")
    for k in ("activations", "simulation"):  # linear in the batch
        assert many[k] == pytest.approx(100 * one[k], rel=0.01)
    assert many["parameters"] == one["parameters"] and many["base"] == one["base"]
    # the saved activations of one sample are at least its input and output images
    assert memory.saved_bytes_per_sample(tr.model, 64) >= 2 * 64 * 64 * 4


@pytest.mark.parametrize("task", ["baseline", "joint"])
def test_a_batch_the_machine_cannot_hold_is_refused_before_any_work(tmp_path, monkeypatch, capsys, task):
    monkeypatch.setattr(memory, "available_bytes", lambda device: (8 * 2**30, "MemAvailable in /proc/meminfo"))
    line = config_error(monkeypatch, capsys, tmp_path / "run", f"+experiment={task}", "debug=smoke",
                        "data.batch_size=100000")
    assert re.fullmatch(rf"codesign: configuration error: data.batch_size = 100000: \+experiment={task} \(batch "
                        r"100000 per process\) needs about [0-9.]+ GiB \(parameters [0-9.]+, activations [0-9.]+, "
                        r"simulation [0-9.]+, base 0.50 GiB\) but 8.0 GiB are available \(MemAvailable in "
                        r"/proc/meminfo\): lower data.batch_size \(activations and simulation grow with it\), "
                        r"data.padded_size / data.image_size, or model.size", line), line


def test_the_machine_says_how_much_is_available():
    import torch

    free, source = memory.available_bytes(torch.device("cpu"))
    assert free is None or free > 0
    assert source in ("MemAvailable in /proc/meminfo", "available physical pages", "unknown")
