"""Fixtures shared by the design tests."""
from __future__ import annotations

import pytest

from tests.cli import run_codesign


@pytest.fixture(scope="session")
def mask_search_smoke(tmp_path_factory):
    """One smoke-size ``+experiment=mask_search`` run (its folder and console output), read by every test that
    checks what such a run writes (outputs, mask.init round trip, TensorBoard), never written to: one run of ~8 s
    instead of one per test module."""
    run_dir = tmp_path_factory.mktemp("mask_search") / "run"
    proc = run_codesign("+experiment=mask_search", "debug=smoke", "threads=1", f"hydra.run.dir={run_dir}")
    assert proc.returncode == 0, proc.stderr[-4000:]
    return run_dir, proc.stdout + proc.stderr
