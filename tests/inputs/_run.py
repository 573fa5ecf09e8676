"""Run an experiment in-process on a composed config, with the heavy work replaced by a sentinel, and return what
the user would read on stderr. A bad value must stop the run before the sentinel (i.e. before any work)."""
from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir

from codesign.config.runtime import command_line_keys
import codesign.experiments as experiments
from tests.conftest import REPO_ROOT


class WorkStarted(Exception):
    """The run got past validation into real work (PSF timing, simulation, training, search, restoration)."""


def _work(*args, **kwargs):
    raise WorkStarted


def _camera_without_optics(build):
    """``build_camera`` whose camera starts work (the sentinel) when its optics are first asked for."""
    def wrapped(*args, **kwargs):
        camera = build(*args, **kwargs)
        camera.frozen_optics = _work
        return camera
    return wrapped


def stop_before_work(monkeypatch) -> None:
    """Replace the first expensive step of every experiment with the sentinel."""
    import codesign.experiments.export as export
    import codesign.experiments.joint as joint
    import codesign.experiments.tolerance as tolerance
    import codesign.experiments.psf as psf
    import codesign.experiments.baseline as restoration
    import codesign.experiments.evaluate as evaluate
    import codesign.experiments.restore as restore
    import codesign.experiments.mask_search as search
    import codesign.experiments.simulate as simulate

    monkeypatch.setattr(psf, "time_forward_backward", _work)
    monkeypatch.setattr(simulate, "build_camera", _camera_without_optics(simulate.build_camera))
    monkeypatch.setattr(restoration.Trainer, "fit", _work)
    monkeypatch.setattr(restoration, "run_evaluation", _work)
    monkeypatch.setattr(evaluate, "run_evaluation", _work)
    monkeypatch.setattr(joint, "_train", _work)
    monkeypatch.setattr(search.MaskSearch, "run", _work)
    monkeypatch.setattr(restore, "build_camera", _camera_without_optics(restore.build_camera))
    monkeypatch.setattr(export, "OpticalSystem", _work)
    monkeypatch.setattr(tolerance, "OpticalSystem", _work)


def compose_cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def config_error(monkeypatch, capsys, run_dir, *overrides: str) -> str:
    """The ``codesign: configuration error: ...`` line of a run that must exit with 2 before any work."""
    stop_before_work(monkeypatch)
    # under Hydra the typed keys win over debug=smoke's shrink; give run_experiment the same knowledge here
    monkeypatch.setattr(experiments, "explicit_keys", lambda: command_line_keys(list(overrides)))
    cfg = compose_cfg(*overrides)
    with pytest.raises(SystemExit) as info:
        experiments.run_experiment(cfg, run_dir=run_dir)
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    return err[-1]
