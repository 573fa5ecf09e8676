"""What a newcomer finds without reading the code: ``--help`` lists every experiment and the ``+experiment=`` form,
``--version`` prints codesign's version, the LICENSE says MIT as pyproject does, docs/config.md is the current
reference of every config key, and a smoke-size mask_search says its failures are expected at that size."""
from __future__ import annotations

import logging
import re
import tomllib
from pathlib import Path

from omegaconf import OmegaConf

from tests.cli import run_codesign

ROOT = Path(__file__).resolve().parent.parent


def test_help_lists_every_experiment_and_the_plus_form():
    from codesign.experiments import EXPERIMENTS, protocol

    proc = run_codesign("--help")
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = proc.stdout
    assert "+experiment=NAME" in out
    for name in EXPERIMENTS:
        assert re.search(rf"^\s+{name}\s+{re.escape(protocol(name).summary)}$", out, re.M), name
    for pointer in ("bash install.sh && python -m codesign +experiment=joint", "bash install.sh && python -m pytest",
                    "--cfg job", "docs/config.md", "--hydra-help", "--version"):
        assert pointer in out, pointer
    assert "Hydra" not in out.splitlines()[0]  # codesign's help, not Hydra's
    short = run_codesign("-h")
    assert short.returncode == 0 and short.stdout == out


def test_version_is_codesigns_and_pyprojects():
    import codesign

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert codesign.__version__ == project["version"]
    proc = run_codesign("--version")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout == f"codesign {codesign.__version__}\n"


def test_hydra_help_is_still_hydras():
    proc = run_codesign("--hydra-help")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "Hydra" in proc.stdout and "--cfg" in proc.stdout


def test_license_is_mit_as_pyproject_says():
    text = (ROOT / "LICENSE").read_text()
    assert tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["license"] == {"text": "MIT"}
    assert text.startswith("MIT License")
    assert "Copyright (c) 2026 the codesign authors" in text
    assert "THE SOFTWARE IS PROVIDED \"AS IS\"" in text


def test_config_reference_is_current():
    from codesign.config.reference import OUTPUT, generate

    assert OUTPUT == ROOT / "docs" / "config.md"
    text = generate()
    assert OUTPUT.read_text() == text, "docs/config.md is stale: run python -m codesign.config.reference"
    # every group of the default config has its section, and each key of the composed defaults its row
    root = OmegaConf.load(ROOT / "conf" / "config.yaml")
    groups = [next(iter(d)) for d in root.defaults if isinstance(d, dict)]
    for group in groups:
        if group in ("preset", "debug"):
            continue  # sizes and the debug shrink: overrides of the keys documented here, not keys of their own
        assert f"\n## {group}\n" in text, group
    for group in ("optics", "sensor", "trainer", "search", "codesign", "export", "tolerance", "simulate"):
        assert f"\n## {group}\n" in text, group
    assert "| `optics.pupil_pitch_m` | `9.974e-06` | pupil_pitch_m: pupil sample pitch Delta_u [m]" in text
    assert "| `sensor.exposure_s` | `0.1` | exposure_s: default exposure t [s]" in text


def test_smoke_note_only_under_debug_smoke():
    from codesign.experiments import SMOKE_NOTE, _SmokeNote, smoke_active

    assert smoke_active(OmegaConf.create({"debug": {"name": "smoke", "overrides": {}}}))
    assert not smoke_active(OmegaConf.create({"debug": None}))
    assert not smoke_active(OmegaConf.create({"task": "psf"}))
    record = logging.LogRecord("codesign.mask_search", logging.ERROR, __file__, 1, "NO FEASIBLE POINT in %d", (3,),
                               None)
    plain = logging.LogRecord("codesign.mask_search", logging.ERROR, __file__, 1, "NO FEASIBLE POINT in %d", (3,),
                              None)
    record.smoke_expected = True
    assert _SmokeNote().filter(record) and _SmokeNote().filter(plain)
    assert record.getMessage() == f"NO FEASIBLE POINT in 3 ({SMOKE_NOTE})"
    assert plain.getMessage() == "NO FEASIBLE POINT in 3"  # a record not marked keeps its words


def test_smoke_mask_search_says_its_failures_are_expected(tmp_path):
    # an MTF floor that 16 evaluations on the smoke grid cannot reach: no feasible point, and a failed re-check
    proc = run_codesign("+experiment=mask_search", "debug=smoke", "threads=1", "search.mtf_floor=0.3",
                        f"hydra.run.dir={tmp_path / 'run'}", timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout + proc.stderr
    failing = [line for line in out.splitlines() if "NO FEASIBLE POINT" in line or "re-check FAILS" in line
               or "does NOT survive the re-check" in line or "does NOT resolve its phase" in line]
    assert any("NO FEASIBLE POINT" in line for line in failing), out[-3000:]
    assert any("does NOT resolve its phase" in line for line in failing), out[-3000:]  # the coarse smoke grid
    assert any("re-check FAILS" in line for line in failing), out[-3000:]
    for line in failing:
        assert "expected at smoke size" in line, line
