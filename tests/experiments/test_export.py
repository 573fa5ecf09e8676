"""``+experiment=export`` and ``+experiment=tolerance`` on the published mask and on a searched design (debug=smoke):
the files a shop gets agree with each other and with the metrics, and the tolerance run's nominal sample is the
exported design (bad settings: tests/inputs/test_config_values.py)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from codesign.fab.writers import read_height_png, read_height_tiff
from tests.cli import run_codesign
from tests.conftest import REPO_ROOT

SEARCHED = REPO_ROOT / "benchmarks/results/full/design/restorability_published/best_mask.json.gz"  # a spline design


def _run(tmp: Path, name: str, *args: str) -> Path:
    run_dir = tmp / name
    proc = run_codesign(*args, "debug=smoke", f"hydra.run.dir={run_dir}", timeout=240)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return run_dir


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("export")
    return {
        "published": _run(tmp, "published", "+experiment=export"),
        "searched": _run(tmp, "searched", "+experiment=export", f"mask.init={SEARCHED}", "export.levels=4",
                         "material=su8"),
        "tolerance": _run(tmp, "tolerance", "+experiment=tolerance", f"mask.init={SEARCHED}", "export.levels=4",
                          "material=su8"),
    }


def test_export_files_agree(runs):
    for name in ("published", "searched"):
        d = runs[name]
        height = np.load(d / "height_m.npy")
        side = json.loads((d / "export.json").read_text())
        m = json.loads((d / "metrics.json").read_text())
        assert height.shape == (side["n"], side["n"]) and side["pitch_m"] == 8e-6  # debug=smoke's pitch
        assert side["max_depth_m"] == pytest.approx(height.max(), rel=1e-12) == m["max_depth_m"]
        assert side["full_wave_depth_m"] == pytest.approx(633e-9 / (side["refractive_index"] - 1), rel=1e-12)
        png, scale, meta = read_height_png(d / "height.png")
        assert meta == side and scale == side["metres_per_count"]
        assert np.abs(png - height).max() <= 0.5 * scale * (1 + 1e-9)
        tif, tmeta = read_height_tiff(d / "height.tif")
        assert tmeta == side and np.array_equal(tif, png)
        assert (d / "report.png").stat().st_size > 10_000
        for k in ("lsr", "mtf_mean", "lsr_over_limit", "restorability"):
            assert np.isfinite(m[f"ideal_{k}"]) and np.isfinite(m[f"exported_{k}"])
    pub = json.loads((runs["published"] / "metrics.json").read_text())
    assert pub["levels"] is None and pub["material"] == "fused_silica"
    assert abs(pub["lsr_change"]) < 0.1  # a continuous plate at 8 um keeps the design within the sampling check
    searched = json.loads((runs["searched"] / "export.json").read_text())
    assert searched["levels"] == 4 and searched["design"]["kind"] == "spline" and searched["material"] == "su8"
    h = np.load(runs["searched"] / "height_m.npy")
    steps = h / searched["level_step_m"]
    assert np.allclose(steps, np.round(steps), atol=1e-9) and set(np.unique(np.round(steps))) <= {0, 1, 2, 3}
    assert searched["max_depth_m"] == pytest.approx(0.75 * searched["full_wave_depth_m"], rel=1e-12)


def test_tolerance_nominal_is_the_export(runs):
    exported = json.loads((runs["searched"] / "metrics.json").read_text())
    tol = json.loads((runs["tolerance"] / "metrics.json").read_text())
    assert tol["nominal_lsr"] == pytest.approx(exported["exported_lsr_sampled"], rel=1e-6)
    assert tol["nominal_mtf_mean"] == pytest.approx(exported["exported_mtf_mean"], rel=1e-6)
    assert set(tol["sources"]) == {"depth_scale", "level_noise", "shift", "rotation", "wavelength", "defocus"}
    assert 0.0 <= tol["yield"] <= 1.0 and tol["lsr_ceiling"] == pytest.approx(1.2 * tol["nominal_lsr"])
    assert "lsr_at_plus_1sigma" in tol["sources"]["shift"] and "lsr_at_plus_1sigma" not in tol["sources"]["level_noise"]
    rows = (runs["tolerance"] / "samples.csv").read_text().splitlines()
    assert len(rows) == 1 + 6 * 4 + 16  # debug=smoke: 4 per source, 16 at once
