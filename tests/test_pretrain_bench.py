"""benchmarks.pretrain (the shipped restorer's training) rehearsed on a CPU: every run trains, writes its weights-only
checkpoint, and the record names the pool it trained over."""
from __future__ import annotations

import json

import pytest

from benchmarks import pretrain


@pytest.mark.slow  # 60 s: three 2-step trainings at the main job's sizes
def test_pretrain_dry_run_writes_every_runs_weights(tmp_path):
    assert pretrain.main(["--out", str(tmp_path), "--dry-run"]) == 0
    record = json.loads((tmp_path / "pretrain.json").read_text())
    assert set(record["runs"]) == set(pretrain.RUNS)
    assert record["pool"] == pretrain.POOL
    for name, run in record["runs"].items():
        assert run["exit"] == 0 and run["steps"] == 2
        assert (tmp_path / f"{name}.pt").stat().st_size < 20 * 2**20
    assert [m["mask"] for m in record["runs"]["pool_seed0"]["mask_pool"]] == pretrain.POOL


def test_unknown_run_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        pretrain.main(["--out", str(tmp_path), "--runs", "pool_seed0,bogus"])
    assert ("--runs: unknown ['bogus']; allowed: pool_seed0, pool_seed1, single or pool_seed<k> (the pool with "
            "seed k)") in capsys.readouterr().err
