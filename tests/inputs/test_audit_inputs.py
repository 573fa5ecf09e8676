"""Issue 59's audit of the inputs beside the run folder: the user's file in an API run_dir stays byte for byte, a
resume under other trainer.* settings says which, a corrupt image of a folder source is skipped, evaluate and
restore say which value of a typed key they used, and restore names the files it skips and an over-range capture."""
from __future__ import annotations

import copy
import hashlib
import logging
import os

import pytest

import codesign
from codesign.errors import ConfigError
from codesign.experiments import resume
from codesign.train.checkpoint import save_checkpoint
from tests.inputs._run import fresh_run_folder_state  # noqa: F401 (autouse: the guard's records, fresh per test)
from tests.train._util import tiny_cfg


def _fingerprint(path):
    st = os.stat(path)
    return hashlib.sha256(path.read_bytes()).hexdigest(), st.st_mtime_ns, st.st_ino, st.st_size


def test_mask_search_into_a_folder_of_the_users_leaves_their_file_untouched(tmp_path):
    """The auditor saw the planted best_mask.json changed: the guard refuses before anything is written there."""
    mine = tmp_path / "D" / "best_mask.json"
    mine.parent.mkdir()
    mine.write_text('{"mine": [1, 2, 3]}')
    before = _fingerprint(mine)
    with pytest.raises(ConfigError, match=r"^run_dir = .*: holds files that no codesign run wrote \(best_mask.json\)"):
        codesign.mask_search("debug=smoke", run_dir=mine.parent)
    assert _fingerprint(mine) == before and sorted(p.name for p in mine.parent.iterdir()) == ["best_mask.json"]


def test_a_resume_under_other_trainer_settings_names_each_with_both_values(trained, tmp_path, monkeypatch, caplog):
    cfg = tiny_cfg("trainer.lr_weights=0.01")
    saved = copy.deepcopy(trained["config"])
    state = {**trained, "config": saved, "opt_g": {}, "opt_d": {}, "sched_g": {}, "sched_d": {}, "rng": {}}
    path = save_checkpoint(tmp_path / "checkpoint.pt", state)
    monkeypatch.setattr(resume, "resume_trainer", lambda *a: None)  # the weights' loading is tested elsewhere
    with caplog.at_level(logging.INFO, logger="codesign.train"):
        resume.resume_if_possible(object(), cfg, tmp_path)
    lines = [r.getMessage() for r in caplog.records if "other training settings" in r.getMessage()]
    assert lines == [f"trainer.resume = '{path}': resumed with other training settings than the checkpoint's: "
                     f"trainer.lr_weights = {saved['trainer']['lr_weights']!r} there, 0.01 here"]
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="codesign.train"):
        resume.resume_if_possible(object(), tiny_cfg(), tmp_path)  # the same settings: nothing said
    assert not [r for r in caplog.records if "other training settings" in r.getMessage()]
