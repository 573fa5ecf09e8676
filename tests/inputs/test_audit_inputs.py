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


def _folder_with_a_nan_image(folder):
    import numpy as np
    import tifffile
    from PIL import Image

    folder.mkdir()
    nan = np.random.default_rng(0).random((48, 48)).astype(np.float32)
    nan[3, 3] = np.nan
    tifffile.imwrite(folder / "a_nan.tif", nan)
    Image.fromarray(np.full((48, 48), 128, np.uint8)).save(folder / "good.png")
    return folder


def test_simulate_skips_a_folder_image_whose_pixels_are_nan_with_the_corrupt_files_warning(tmp_path):
    """The audit's case: a float TIFF with NaN pixels passed the folder's probe and ended simulate in a traceback."""
    from codesign.data.images import SceneLoadWarning
    from codesign.data.source import SceneSource
    from codesign.experiments.simulate import _readable_scenes

    source = SceneSource.from_folder(_folder_with_a_nan_image(tmp_path / "F"), test_fraction=0.5)
    skipped = r"^data.folder: skipped unreadable image a_nan.tif \(.*non-finite samples"
    with pytest.warns(SceneLoadWarning, match=skipped):
        assert _readable_scenes(source, 2, 32) == ["good.png"]
    (tmp_path / "F" / "good.png").unlink()
    source = SceneSource.from_folder(tmp_path / "F")
    with pytest.warns(SceneLoadWarning), pytest.raises(ConfigError, match=r"^data.folder = .*F': holds no image that "
                                                                         r"decodes \(each was skipped above\)$"):
        _readable_scenes(source, 1, 32)
