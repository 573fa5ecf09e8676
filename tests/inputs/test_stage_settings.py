"""A multi-stage run (the main job, +experiment=joint) reuses a finished or started stage on a restart only with the
settings that stage was made with (issue 59 item 2): each stage records them (codesign/train/stage_settings.py),
a restart compares before any work and refuses a difference naming each key with both values."""
from __future__ import annotations

import json
import logging

import pytest

import codesign.experiments as experiments
from codesign.config.runtime import to_container
from codesign.errors import ConfigError
from codesign.train import stage_settings
from tests.inputs._run import compose_cfg, config_error
from tests.inputs._run import fresh_run_folder_state  # noqa: F401 (autouse: the guard's records, fresh per test)

RECORD = "stage_settings.json"
SMALL = {"seed": 0, "device": "cpu", "codesign": {"lsr_max": None, "finetune_steps": 240},
         "trainer": {"steps": 400, "checkpoint_every": 100}, "evaluate": {"laser_strengths": [0, 1e6]}}


def _changed(**changes) -> dict:
    cfg = json.loads(json.dumps(SMALL))
    for dotted, value in changes.items():
        *parents, leaf = dotted.split("__")
        node = cfg
        for p in parents:
            node = node[p]
        node[leaf] = value
    return cfg


def test_the_settings_a_stage_records_leave_out_how_the_run_executes():
    assert stage_settings.settings(SMALL) == {"seed": 0, "codesign.lsr_max": None, "codesign.finetune_steps": 240,
                                              "trainer.steps": 400, "evaluate.laser_strengths": [0, 1e6]}


def test_the_compare_names_every_differing_key_with_both_values():
    old = stage_settings.settings(SMALL)
    new = stage_settings.settings(_changed(seed=1, codesign__lsr_max=1e-3, device="cuda", trainer__checkpoint_every=5))
    assert stage_settings.differences(old, new) == [("codesign.lsr_max", None, 1e-3), ("seed", 0, 1)]
    more = stage_settings.settings(_changed(codesign__finetune_steps=480))
    assert stage_settings.differences(old, more) == [("codesign.finetune_steps", 240, 480)]
    assert stage_settings.differences(old, more, ignored=("codesign.finetune_steps",)) == []
    fewer = {k: v for k, v in old.items() if k != "seed"}  # a key one side lacks
    assert stage_settings.differences(fewer, old) == [("seed", "(absent)", 0)]


def test_a_stage_made_with_other_settings_is_refused_and_kept(tmp_path):
    folder = tmp_path / "run" / "restorer"
    stage_settings.begin_stage(folder, "restorer", stage_settings.settings(SMALL))
    (folder / "metrics.json").write_text("{}")
    before = (folder / RECORD).read_bytes()
    new = stage_settings.settings(_changed(seed=1, codesign__lsr_max=1e-3))
    with pytest.raises(ConfigError) as info:
        stage_settings.check_stage(folder, "restorer", new)
    assert str(info.value) == (
        f"codesign.lsr_max = 0.001: the stage restorer/ of this run folder ({tmp_path / 'run'}) was made with other "
        f"settings, which a restart would reuse under this run's: codesign.lsr_max = None there, 0.001 here; seed = "
        f"0 there, 1 here; a stage is reused only with the settings it was made with: restart with those, or start "
        f"this run in a new folder (hydra.run.dir=PATH, or leave it unset: every run gets a new one)")
    stage_settings.check_stage(folder, "restorer", stage_settings.settings(_changed(device="cuda")))  # executes only
    stage_settings.begin_stage(folder, "restorer", new)  # a recorded stage keeps its record
    assert (folder / RECORD).read_bytes() == before


def test_a_stage_of_an_earlier_version_is_reused_with_a_warning_and_no_record(tmp_path, caplog):
    folder = tmp_path / "run" / "restorer"
    folder.mkdir(parents=True)
    (folder / "checkpoint.pt").write_bytes(b"an earlier version's")
    with caplog.at_level(logging.WARNING, logger="codesign.main_job"):
        stage_settings.check_stage(folder, "restorer", stage_settings.settings(SMALL))
    assert "stage restorer/ has no stage_settings.json (made before codesign recorded each stage's settings)" in \
        caplog.text
    stage_settings.begin_stage(folder, "restorer", stage_settings.settings(SMALL))
    assert not (folder / RECORD).exists()  # what its files were made with is unknown: never certified now
    (folder / RECORD).write_text("not json")
    with pytest.raises(ConfigError, match="is not a stage settings record"):
        stage_settings.check_stage(folder, "restorer", {})


SMOKE = ("+experiment=joint", "debug=smoke")


def _recorded_stage(run_dir, stage: str, *overrides: str) -> None:
    """A finished stage of a killed main job, its record as the main job writes it for ``overrides``."""
    cfg = compose_cfg(*SMOKE, *overrides)
    experiments.apply_debug(cfg, frozenset())
    stage_settings.begin_stage(run_dir / stage, stage, stage_settings.settings(to_container(cfg)))
    (run_dir / stage / "metrics.json").write_text("{}")


def test_a_restarted_main_job_refuses_stages_made_with_another_seed_before_any_work(tmp_path, monkeypatch, capsys):
    """The audit's case: a killed joint restarted on its folder with another seed (or codesign.lsr_max) reused the
    stages made under the old settings and labelled the result with the new ones."""
    run_dir = tmp_path / "run"
    _recorded_stage(run_dir, "restorer", "seed=0")
    line = config_error(monkeypatch, capsys, run_dir, *SMOKE, "seed=1")
    assert line == (f"codesign: configuration error: search.seed = 1: the stage restorer/ of this run folder "
                    f"({run_dir}) was made with other settings, which a restart would reuse under this run's: "
                    f"search.seed = 0 there, 1 here; seed = 0 there, 1 here; a stage is reused only with the settings "
                    f"it was made with: restart with those, or start this run in a new folder (hydra.run.dir=PATH, or "
                    f"leave it unset: every run gets a new one)")  # search.seed: ${seed}
    assert not (run_dir / "design").exists()  # refused before the design stage
    # every stage of a main job records its settings: tests/experiments/test_main_job.py
