"""``python -m codesign +experiment=simulate debug=smoke``: files, 16-bit captures and metrics."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.cli import run_codesign


@pytest.fixture(scope="module")
def simulate_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("simulate") / "run"
    proc = run_codesign("+experiment=simulate", "debug=smoke", f"hydra.run.dir={run_dir}", timeout=180)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return run_dir


def test_simulate_writes_grids_captures_and_metrics(simulate_run):
    for name in ("sensor_grid_linear.png", "sensor_grid_log.png", "metrics.json", "example_sensor.npy",
                 "example_irradiance_target.npy", "example_scene_target.npy"):
        assert (simulate_run / name).is_file(), name
    captures = sorted((simulate_run / "captures").glob("sensor_*_alpha_l_*.png"))
    assert len(captures) == 2  # debug=smoke: one scene, alpha_l in {0, 1e6}
    for path in captures:
        img = np.asarray(Image.open(path))
        assert img.dtype == np.uint16 and img.shape == (256, 256)
    m = json.loads((simulate_run / "metrics.json").read_text())
    assert m["saturated_fraction_alpha_l_0"] == 0.0
    assert 0.0 < m["saturated_fraction_alpha_l_1e6"] < 0.2
    assert m["laser_peak_alpha_l_0"] == 0.0 and m["laser_peak_alpha_l_1e6"] > 1.0
    assert 0.0 < m["bsr"] <= 1.0 and 0.0 < m["lsr_sampled"] < 0.1
    assert m["seconds_per_image"] > 0 and m["sensor_path"] == "direct"
    # the 16-bit capture is the counts: a saturated laser pixel reads G e_sat = 0.37 * 25500 = 9435 DN
    hot = np.asarray(Image.open(next(c for c in captures if "1e6" in c.name)))
    assert int(hot.max()) == 9435
    net = np.load(simulate_run / "example_sensor.npy")
    assert net.shape == (384, 384) and float(np.abs(net[:64]).max()) == 0.0  # zero padding 256 -> 384
