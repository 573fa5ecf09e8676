"""The main job over seeds (benchmarks/main_job_seeds.py): its per-seed rows from the main job's metrics.json, the
spread over seeds and the joint stage's verdict, and the checks that refuse runs which cannot make one spread."""
from __future__ import annotations

import json

import pytest

from benchmarks import main_job_seeds as seeds

ALPHAS = seeds.ALPHAS


def _metrics(seed: int, designed: float, codesigned: float, **settings) -> dict:
    """A main job's metrics.json, reduced to what the table reads: the systems' PSNR matched at every alpha_l
    (the same at every alpha_l here), the stage gains the run printed, the goal."""
    systems = {name: {f"laser_{a}": {"psnr_matched": v} for a in ALPHAS}
               for name, v in (("designed_network", designed), ("codesigned_network", codesigned))}
    gains = {key: {f"laser_{a}": {"mean": g, "interval": 0.5} for a in ALPHAS}
             for key, g in ((seeds.TOTAL, codesigned - 22.0), (seeds.JOINT, codesigned - designed))}
    return {"protocol": "codesign", "seed": seed, "minutes": 14.0, "lsr_published_peak": 8e-3,
            "masks": {"co-designed": {"lsr": 1e-3}}, "goal": {"met": codesigned - 22.0 >= 3.0},
            "systems": systems, "gains": gains, "lsr_max_from": "1/8", "network": "sgan_b_l1",
            "trainer_steps": 220, "finetune_steps": 120, "scenes": ["a.png", "b.png"], **settings}


def _write(tmp_path, runs: list[dict]) -> list:
    paths = []
    for k, m in enumerate(runs):
        (tmp_path / f"run{k}").mkdir()
        (tmp_path / f"run{k}" / "metrics.json").write_text(json.dumps(m))
        paths.append(tmp_path / f"run{k}")
    return paths


def test_the_joint_stage_is_paired_by_seed_and_read_against_twice_the_spread(tmp_path):
    # designed 25.0 / 25.4 / 24.6 (sd 0.4); co-designed +1.0 dB at each seed: significant (1.0 > 2 x 0.4)
    runs = [_metrics(s, d, d + 1.0) for s, d in ((2, 24.6), (0, 25.0), (1, 25.4))]
    out = tmp_path / "out"
    assert seeds.main(["--out", str(out), "--runs", *map(str, _write(tmp_path, runs))]) == 0
    res = json.loads((out / "seeds.json").read_text())
    assert list(res["rows"]) == ["0", "1", "2"]  # ordered by seed, whatever the order given
    assert res["rows"]["1"]["lsr_ratio"] == pytest.approx(0.125)
    j = res["summary"]["joint_vs_frozen"]["1e6"]
    assert j["gain"] == pytest.approx(1.0) and j["spread"] == pytest.approx(0.4) and j["gain_std"] < 1e-9
    assert res["summary"]["joint_goal_met"] is True and res["summary"]["main_job_goal_every_seed"] is True
    total = res["summary"]["over_seeds"]["total_1e6"]
    assert total["mean"] == pytest.approx(4.0) and total["std"] == pytest.approx(0.4)
    md = (out / "seeds.md").read_text()
    assert "| 1 | 14.0 | 0.125 | +4.40 +- 0.50 |" in md
    assert "+1.00 dB, paired sd 0.00, seed spread 0.40" in md and "beyond twice the spread): met" in md


@pytest.mark.parametrize("designed, joint, why", [
    ((25.0, 25.4, 24.6), 0.7, "within twice the spread (2 x 0.4)"),
    ((25.0, 25.02, 24.98), 0.45, "beyond twice the spread (2 x 0.02) but below +0.5 dB"),
])
def test_the_joint_goal_is_missed_below_half_a_db_or_within_the_spread(designed, joint, why):
    runs = [_metrics(s, d, d + joint) for s, d in enumerate(designed)]
    res = seeds.summarize({m["seed"]: seeds.per_seed_row(m) for m in runs})
    assert res["joint_vs_frozen"]["1e6"]["significant"] is (joint < 0.5)
    assert res["joint_goal_met"] is False, why


def test_runs_of_different_settings_or_the_same_seed_are_refused(tmp_path):
    other = _write(tmp_path, [_metrics(0, 25.0, 26.0), _metrics(1, 25.0, 26.0, lsr_max_from="1/4")])
    with pytest.raises(SystemExit, match=r"seed 1 differs from seed 0 in \['lsr_max_from'\]"):
        seeds.load_runs(other)
    (tmp_path / "x").mkdir()
    twice = _write(tmp_path / "x", [_metrics(3, 25.0, 26.0), _metrics(3, 25.0, 26.0)])
    with pytest.raises(SystemExit, match="seed 3 twice"):
        seeds.load_runs(twice)
    (tmp_path / "y").mkdir()
    single = _write(tmp_path / "y", [{**_metrics(0, 25.0, 26.0), "protocol": "single"}, _metrics(1, 25.0, 26.0)])
    with pytest.raises(SystemExit, match="is not a main job .protocol 'single', expected 'codesign'"):
        seeds.load_runs(single)


@pytest.mark.parametrize("argv, message", [
    (["--seeds", "0"], "a spread over seeds needs at least 2 runs"),
    (["--seeds", "1", "1"], "--seeds [1, 1]: each seed once"),
    (["--set", "seed=4"], "the seed and the run folder are set per seed"),
    (["--set", "codesign.lsr_max"], "--set 'codesign.lsr_max': must be KEY=VALUE"),
    (["--runs", "/nonexistent/run"], "no metrics.json (not a finished main-job folder)"),
])
def test_bad_arguments_stop_before_any_run(argv, message, tmp_path, capsys):
    with pytest.raises(SystemExit):
        seeds.parse_args(["--out", str(tmp_path), *argv])
    assert message in capsys.readouterr().err
