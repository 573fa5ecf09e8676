"""docs/tutorial.md runs as printed: its script (docs/tutorial.py) runs every command at smoke size, in order, and
every picture the page shows is written by one of them."""
from __future__ import annotations

import importlib.util
import os
import re
import shlex
import subprocess
import sys

import pytest

from tests.conftest import REPO_ROOT

PAGE = REPO_ROOT / "docs" / "tutorial.md"


def _script():
    spec = importlib.util.spec_from_file_location("tutorial_script", REPO_ROOT / "docs" / "tutorial.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_picture_of_the_page_has_a_source_and_every_step_its_own_folder():
    script = _script()
    shown = set(re.findall(r"!\[[^]]*\]\(tutorial/([^)]+)\)", PAGE.read_text()))
    assert shown == set(script.PICTURES)
    cmds = script.commands()
    assert len(cmds) == 11 and all(c.startswith("python -m codesign +experiment=") for c in cmds)
    dirs = [re.search(r"hydra.run.dir=(\S+)", c).group(1) for c in cmds]
    assert len(set(dirs)) == len(dirs) and all(d.startswith("outputs/tutorial/") for d in dirs)
    for step in ("mask_search", "psf", "simulate", "baseline", "evaluate", "joint", "export", "tolerance", "restore"):
        assert any(f"+experiment={step} " in c for c in cmds), step


def test_every_command_composes():
    """The cheap twin of the smoke run: every command of the tutorial composes with Hydra (each key it sets exists
    in its experiment's configuration)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        for command in _script().commands():
            overrides = [a for a in shlex.split(command)[3:] if not a.startswith("hydra.")]
            cfg = compose("config", overrides=overrides)
            assert cfg.task == re.search(r"\+experiment=(\w+)", command).group(1)


@pytest.mark.slow  # 94 s: every command of the tutorial in turn; twin: test_every_command_composes
def test_the_tutorial_runs_at_smoke_size(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "2", "MKL_NUM_THREADS": "2"}
    proc = subprocess.run([sys.executable, str(REPO_ROOT / "docs" / "tutorial.py"), "--smoke", "--root",
                           str(tmp_path), "--pictures", str(tmp_path / "pictures")], env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, (proc.stdout[-3000:], proc.stderr[-3000:])
    assert proc.stdout.count(" ok in ") == 11
    for name in _script().PICTURES:
        assert (tmp_path / "pictures" / name).stat().st_size > 1000, name
    # run again on the same folder: refused, nothing run over
    again = subprocess.run([sys.executable, str(REPO_ROOT / "docs" / "tutorial.py"), "--smoke", "--root",
                            str(tmp_path)], env=env, capture_output=True, text=True, timeout=60)
    assert again.returncode != 0 and "a finished step is not run over" in again.stderr
