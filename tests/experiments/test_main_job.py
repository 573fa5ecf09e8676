"""The main job's whole protocol at smoke size (``+experiment=joint debug=smoke``: codesign.protocol=codesign): the
design stage, the two restorer stages, the three arms, and the summary built from their evaluations; a second run
on the same folder redoes nothing. One joint run alone (each stage): tests/experiments/test_joint.py."""
from __future__ import annotations

import json
import shutil

import pytest

from codesign.experiments.main_job import STAGES
from codesign.train.protocol_summary import GAINS, SYSTEMS, protocol_summary
from codesign.train.summary import paired_difference
from tests.cli import run_codesign

EVALUATED = ("designed", "codesigned", "published")


@pytest.fixture(scope="module")
def main_job(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("main_job") / "run"
    proc = run_codesign("+experiment=joint", "debug=smoke", f"hydra.run.dir={run_dir}", timeout=400)
    assert proc.returncode == 0, proc.stderr[-4000:]
    (run_dir.parent / "console.txt").write_text(proc.stdout + proc.stderr)
    return run_dir


def _metrics(folder):
    return json.loads((folder / "metrics.json").read_text())


def test_every_stage_runs_in_its_folder_from_the_right_start(main_job):
    for stage in STAGES:
        assert (main_job / stage / "metrics.json").is_file(), stage
    for name in ("summary.txt", "systems.png", "learned_mask.json", "stage_seconds.json", "design/best_mask.json"):
        assert (main_job / name).is_file(), name
    for stage in STAGES:  # the settings that shaped each stage (a restart compares them: tests/inputs/)
        record = json.loads((main_job / stage / "stage_settings.json").read_text())
        assert record["stage"] == stage and record["settings"]["seed"] == 0, stage
    design = _metrics(main_job / "design")
    assert design["mask_kind"] == "spline" and design["objective"] == "restorability"
    steps = {s: _metrics(main_job / s)["steps"] for s in STAGES[1:]}
    assert steps == {"restorer": 4, "published_restorer": 4, "designed": 2, "codesigned": 2, "published": 2}
    starts = {s: _metrics(main_job / s).get("init_checkpoint") for s in STAGES[1:]}
    assert starts == {"restorer": None, "published_restorer": None,
                      "designed": str(main_job / "restorer" / "checkpoint.pt"),
                      "codesigned": str(main_job / "restorer" / "checkpoint.pt"),
                      "published": str(main_job / "published_restorer" / "checkpoint.pt")}
    kinds = {s: _metrics(main_job / s)["mask_kind"] for s in STAGES[1:]}
    assert kinds == {"restorer": "spline", "published_restorer": "halfring", "designed": "spline",
                     "codesigned": "spline", "published": "halfring"}
    # the frozen stages keep their mask; the published stages' mask is the published one
    for s in ("restorer", "designed"):  # the record's controls are written to 7 digits
        assert _metrics(main_job / s)["lsr"] == pytest.approx(design["lsr"], rel=1e-4)
    for s in ("published_restorer", "published"):
        m = _metrics(main_job / s)
        assert m["lsr"] == m["lsr_published"]
    console = (main_job.parent / "console.txt").read_text()
    assert "no pretrained restorer (init.checkpoint=auto): the restorer trains from scratch" in console
    assert "main job: stage 6/6 published" in console


def test_the_joint_stage_keeps_the_certified_peak_under_the_ceiling(main_job):
    m = _metrics(main_job)
    joint, designed = _metrics(main_job / "codesigned"), _metrics(main_job / "designed")
    # default ceiling: a quarter of the published mask's certified peak
    assert m["lsr_max"] == pytest.approx(0.25 * m["lsr_published_peak"], rel=1e-9)
    assert m["lsr_published_peak"] == pytest.approx(m["masks"]["published"]["lsr"], rel=1e-6)
    assert joint["peak_max"] == m["lsr_max"] and joint["lsr_max_from"] == "the start mask's smooth LSR"
    # the guard keeps max(ceiling, the start's peak): a smoke design above the ceiling can only descend
    assert joint["lsr"] <= max(m["lsr_max"], designed["lsr"]) * (1 + 1e-6)
    assert joint["lsr_peak_guarded"] == pytest.approx(joint["lsr"], rel=1e-6)


def test_the_summary_is_the_stages_evaluations(main_job):
    m = _metrics(main_job)
    stages = {s: _metrics(main_job / s) for s in EVALUATED}
    conds = ["laser_0", "laser_1e6"]  # debug=smoke's laser strengths (its robustness stage H1 is not a column)
    assert set(m["systems"]) == set(SYSTEMS) and all(list(row) == conds for row in m["systems"].values())
    for system, (stage, column) in SYSTEMS.items():
        table = stages[stage]["evaluation"]
        for c in conds:
            net = column or m["network"]  # the network's column: its method name (wiener_naf, the main job's)
            assert m["systems"][system][c] == {k: table[c][net][k] for k in ("psnr_matched", "psnr", "ssim")}
    for label, system, against in GAINS:
        for c in conds:
            a, b = m["per_scene_psnr_matched"][system][c], m["per_scene_psnr_matched"][against][c]
            assert len(a) == len(b) == 2
            mean, half = paired_difference(a, b)
            assert m["gains"][label][c] == {"mean": pytest.approx(mean), "interval": pytest.approx(half)}
    assert m["masks"]["co-designed"]["lsr"] == stages["codesigned"]["lsr"]
    assert m["masks"]["published"]["mtf_mean"] == pytest.approx(stages["published"]["mtf_mean_published"], rel=1e-6)
    assert m["scenes"] == ["awning.png", "bridge_city.png"]
    text = (main_job / "summary.txt").read_text()
    assert text == protocol_summary(m) + "\n" and text.rstrip() in (main_job.parent / "console.txt").read_text()
    assert m["network"] == "wiener_naf" and "  co-designed + wiener_naf" in text and "goal (NOT met)" in text  # 4 steps meet no goal


def test_a_second_run_on_the_folder_redoes_nothing(main_job, tmp_path):
    again = tmp_path / "run"
    shutil.copytree(main_job, again)
    proc = run_codesign("+experiment=joint", "debug=smoke", f"hydra.run.dir={again}", timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    log = proc.stdout + proc.stderr
    assert all(f"main job: {s} done before" in log for s in STAGES[1:]) and "design stage done before" in log
    first, second = _metrics(main_job), _metrics(again)
    differ = [k for k in first if first[k] != second[k]]
    assert differ == ["checkpoint"]  # its own folder's; the stage seconds are kept from the first run


@pytest.mark.slow  # 25 s: a second protocol run; twin: test_every_stage_runs_in_its_folder_from_the_right_start
def test_without_a_design_stage_the_published_half_rings_are_the_start(tmp_path):
    """codesign.design=null (the half-ring run): no design stage, the published mask's restorer and frozen arm are
    the published system's (trained once), joint from the published mask under its own certified peak."""
    run_dir = tmp_path / "run"
    proc = run_codesign("+experiment=joint", "debug=smoke", "codesign.design=null", f"hydra.run.dir={run_dir}",
                        timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert sorted(p.name for p in run_dir.iterdir() if p.is_dir() and p.name in STAGES) == \
        ["codesigned", "designed", "restorer"]
    m = _metrics(run_dir)
    assert m["design"] is None and m["lsr_max"] == pytest.approx(m["lsr_published_peak"], rel=1e-9)
    assert m["systems"]["published_network"] == m["systems"]["designed_network"]
    assert _metrics(run_dir / "codesigned")["mask_kind"] == "halfring"
    assert "main job: stage 4/4 codesigned" in proc.stdout + proc.stderr
