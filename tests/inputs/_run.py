"""Run an experiment in-process on a composed config, with the heavy work replaced by a sentinel, and return what
the user would read on stderr. A bad value must stop the run before the sentinel (i.e. before any work)."""
from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir

from codesign.config.runtime import command_line_keys
import codesign.experiments as experiments
from codesign.experiments import rundir, runlock
from tests.conftest import REPO_ROOT


class WorkStarted(Exception):
    """The run got past validation into real work (PSF timing, simulation, training, search, restoration)."""


def _work(*args, **kwargs):
    raise WorkStarted


def _returning_work(factory, attribute: str):
    """``factory`` whose result starts work (the sentinel) when its ``attribute`` is first used."""
    def wrapped(*args, **kwargs):
        made = factory(*args, **kwargs)
        setattr(made, attribute, _work)
        return made
    return wrapped


def stop_before_work(monkeypatch) -> None:
    """Replace the first expensive step of every experiment (its protocol's first_work) with the sentinel."""
    for name in experiments.EXPERIMENTS:
        owner, path = experiments.experiment_module(name), experiments.protocol(name).first_work
        first, _, rest = path.partition(".")
        if first.endswith("()"):  # factory().method: the factory's product starts work
            factory = first[:-2]
            monkeypatch.setattr(owner, factory, _returning_work(getattr(owner, factory), rest))
            continue
        if rest:  # Class.method
            owner, first = getattr(owner, first), rest
        assert hasattr(owner, first), f"{name}: first_work {path} names nothing"
        monkeypatch.setattr(owner, first, _work)


def compose_cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def restore_messages(monkeypatch, caplog, tmp_path, trained: dict, *extra: str,
                     stops: tuple = (WorkStarted,)) -> list[str]:
    """The warnings of ``+experiment=restore`` of the checkpoint ``trained`` (saved in ``tmp_path``) on one flat
    capture of its image size, ``extra`` typed on the command line, up to the first work (``stops``: what may end
    the run there)."""
    import logging

    import numpy as np
    from PIL import Image

    from codesign.experiments import restore
    from codesign.train.checkpoint import save_checkpoint

    path = save_checkpoint(tmp_path / "ck.pt", trained)
    size = trained["config"]["data"]["image_size"]
    Image.fromarray(np.full((size, size), 100, np.uint16)).save(tmp_path / "cap.png")
    overrides = ["+experiment=restore", "debug=smoke", f"checkpoint={path}", f"input={tmp_path / 'cap.png'}",
                 *extra]
    stop_before_work(monkeypatch)
    for module in (experiments, restore):
        monkeypatch.setattr(module, "explicit_keys", lambda: command_line_keys(overrides))
    with caplog.at_level(logging.WARNING, logger="codesign"), pytest.raises(stops):
        experiments.run_experiment(compose_cfg(*overrides), run_dir=tmp_path / "run")
    return [r.getMessage() for r in caplog.records]


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


@pytest.fixture(autouse=True)
def fresh_run_folder_state(monkeypatch):
    """The run-folder guard's records of this process (earlier folders, held locks) as a fresh run finds them: a
    module that binds this fixture to a name has it for every test (tests/inputs/test_run_guard.py and
    test_run_folders.py)."""
    for name in ("EARLIER", "EARLIER_LOGS", "EARLIER_OWN"):
        monkeypatch.setattr(rundir, name, {}, raising=False)
    monkeypatch.setattr(runlock, "HELD", {})
    yield
    for run_dir in list(runlock.HELD):
        runlock.release_lock(run_dir)
