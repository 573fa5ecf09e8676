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


def test_typed_physics_data_and_training_keys_say_which_value_ran():
    from tests.inputs._run import compose_cfg
    from codesign.experiments.typed_values import typed_values_unused

    typed = frozenset({"optics.wavelength_m", "sensor.bit_depth", "data.image_size", "trainer.steps", "seed"})
    cfg = compose_cfg("+experiment=evaluate", "optics.wavelength_m=5e-7", "sensor.bit_depth=12",
                      "data.image_size=64", "trainer.steps=100")
    ckpt = compose_cfg("+experiment=baseline")
    assert typed_values_unused("evaluate", cfg, ckpt, typed) == [
        f"data.image_size = 64 typed, {ckpt.data.image_size!r} used (the checkpoint's)",
        f"optics.wavelength_m = 5e-07 typed, {ckpt.optics.wavelength_m!r} used (the checkpoint's)",
        f"sensor.bit_depth = 12 typed, {ckpt.sensor.bit_depth!r} used (the checkpoint's)",
        "trainer.steps = 100 typed, not used (+experiment=evaluate trains nothing)"]
    assert typed_values_unused("evaluate", ckpt, ckpt, frozenset({"optics.wavelength_m"})) == []  # used as typed


def _stop(*args, **kwargs):
    from tests.inputs._run import WorkStarted

    raise WorkStarted


def test_evaluate_logs_the_typed_keys_it_ran_with_the_checkpoints_values(trained, tmp_path, monkeypatch, caplog):
    import codesign.experiments as experiments
    from codesign.experiments import evaluate
    from tests.inputs._run import WorkStarted, compose_cfg, stop_before_work

    path = save_checkpoint(tmp_path / "ck.pt", trained)
    typed = ("optics.wavelength_m=5e-7", "sensor.bit_depth=12", "trainer.steps=100")
    stop_before_work(monkeypatch)
    monkeypatch.setattr(evaluate, "simulated_data", _stop)  # the line is said before the data is built
    for owner in (evaluate, experiments):  # under Hydra both read the command line: typed keys win over the shrink
        monkeypatch.setattr(owner, "explicit_keys", lambda: frozenset(k.split("=")[0] for k in typed))
    cfg = compose_cfg("+experiment=evaluate", "debug=smoke", f"checkpoint={path}", *typed)
    with caplog.at_level(logging.INFO, logger="codesign.evaluate"), pytest.raises(WorkStarted):
        experiments.run_experiment(cfg, run_dir=tmp_path / "run")
    said = [r.getMessage() for r in caplog.records if "runs the checkpoint with its own settings" in r.getMessage()]
    stored = trained["config"]
    assert said == [f"+experiment=evaluate runs the checkpoint with its own settings: optics.wavelength_m = 5e-07 "
                    f"typed, {stored['optics']['wavelength_m']!r} used (the checkpoint's); sensor.bit_depth = 12 "
                    f"typed, {stored['sensor']['bit_depth']!r} used (the checkpoint's); trainer.steps = 100 typed, "
                    f"not used (+experiment=evaluate trains nothing)"]


def test_restore_names_the_files_it_skips_in_an_input_folder(tmp_path, caplog):
    from codesign.experiments import restore

    (tmp_path / "cap.png").write_bytes(b"")
    (tmp_path / "readme.txt").write_text("notes")
    (tmp_path / ".hidden").write_text("")
    with caplog.at_level(logging.WARNING, logger="codesign.restore"):
        assert restore.input_files(tmp_path) == [tmp_path / "cap.png"]
    assert [r.getMessage() for r in caplog.records] == [
        f"input = '{tmp_path}': skipped 1 entry(ies) that are no .png/.tif/.tiff capture: readme.txt"]


def test_restore_refuses_a_capture_above_the_sensors_full_scale(tmp_path):
    """The audit's 1e9 float TIFF: refused naming its sample type (counts are 16-bit); 16-bit counts above the
    sensor's full scale are refused naming it."""
    import numpy as np
    import tifffile
    from codesign.experiments import restore

    tifffile.imwrite(tmp_path / "big.tif", np.full((8, 8), 1e9, np.float32))
    with pytest.raises(ConfigError, match=r"big.tif': has float32 samples: expected 16-bit sensor counts"):
        restore.validate([tmp_path / "big.tif"], None, 65535.0)
    tifffile.imwrite(tmp_path / "over.tif", np.full((8, 8), 5000, np.uint16))
    with pytest.raises(ConfigError, match=r"over.tif': has counts up to 5000 DN, above the sensor's 4095 DN "
                                          r"\(sensor.bit_depth\)$"):
        restore.validate([tmp_path / "over.tif"], None, 4095.0)


def test_restore_logs_a_typed_data_key_it_ran_with_the_checkpoints_value(trained, tmp_path, monkeypatch, caplog):
    from codesign.experiments import restore
    from tests.inputs._run import restore_messages

    monkeypatch.setattr(restore, "build_camera", _stop)  # the line is said before the camera is built
    said = restore_messages(monkeypatch, caplog, tmp_path, trained, "data.image_size=64")
    size = trained["config"]["data"]["image_size"]
    assert [m for m in said if "its own settings" in m] == [
        f"+experiment=restore runs the checkpoint with its own settings: data.image_size = 64 typed, {size!r} used "
        f"(the checkpoint's)"]
