"""Hydra keys that would have Hydra itself write outside the run folder (issue 59's audit: hydra.output_subdir put
the run's record outside its folder; a log handler's filename appended the run's log to a user's file) are refused
on the command line before Hydra starts, one line naming the key and the value."""
from __future__ import annotations

import sys

import pytest

from codesign.__main__ import main

GUARD = ("codesign writes the run's record (.hydra/) and its log into the run folder itself, through the run-folder "
         "guard; a file of Hydra's elsewhere is not allowed: choose the folder with hydra.run.dir=PATH (or "
         "hydra.sweep.dir=PATH with -m)")


@pytest.mark.parametrize("key", ["hydra.output_subdir", "++hydra.output_subdir",
                                 "hydra.job_logging.handlers.file.filename",
                                 "hydra.hydra_logging.handlers.file.filename"])
def test_a_hydra_key_that_writes_elsewhere_is_refused_before_hydra(key, tmp_path, monkeypatch, capsys):
    victim = tmp_path / "victim.log"
    victim.write_text("the user's\n")
    run_dir = tmp_path / "run"
    monkeypatch.setattr(sys, "argv", ["codesign", "+experiment=psf", "debug=smoke", f"{key}={victim}",
                                      f"hydra.run.dir={run_dir}"])
    with pytest.raises(SystemExit) as info:
        main()
    assert info.value.code == 2
    name = key.lstrip("+")
    assert capsys.readouterr().err.strip() == f"codesign: configuration error: {name} = '{victim}': {GUARD}"
    assert victim.read_text() == "the user's\n" and not run_dir.exists()
