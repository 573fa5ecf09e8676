"""A regular install runs: the wheel of this checkout, installed into a fresh environment without the checkout, runs
the smoke experiments from an unrelated folder (its configs, pretrained weights and held-out photographs inside the
package) and reports its version from the installed metadata."""
from __future__ import annotations

import json
import os
import site
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT


def _run(cmd: list, cwd: Path, timeout: int = 300) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)
    assert proc.returncode == 0, f"{cmd}\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    return proc


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> tuple[Path, Path]:
    """(the environment's python, an unrelated working folder): the wheel built from this checkout and installed
    with pip into a new virtual environment; its dependencies (torch & co., not the point here and gigabytes to
    install) are this interpreter's, put on its path by a .pth line, which adds the folder but runs none of its .pth
    files: the checkout's editable install stays out of it."""
    work = tmp_path_factory.mktemp("wheel")
    _run([sys.executable, "-m", "pip", "wheel", REPO_ROOT, "--no-deps", "--no-build-isolation", "-q", "-w",
          work / "dist"], cwd=work)
    wheel = next((work / "dist").glob("codesign-*.whl"))
    _run([sys.executable, "-m", "venv", work / "env"], cwd=work)
    python = work / "env" / "bin" / "python"
    _run([python, "-m", "pip", "install", "--no-deps", "--no-index", "-q", wheel], cwd=work)
    env_site = Path(_run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                         cwd=work).stdout.strip())
    deps = {sysconfig.get_paths()["purelib"], *site.getsitepackages()}
    (env_site / "codesign_test_deps.pth").write_text("\n".join(sorted(deps)) + "\n")
    elsewhere = work / "elsewhere"
    elsewhere.mkdir()
    return python, elsewhere


def test_the_installed_package_is_the_wheels_with_its_configs(installed):
    python, elsewhere = installed
    where = _run([python, "-c", "import codesign, codesign.config as c; print(codesign.__file__); "
                  "print(sorted(p.name for p in c.CONF_DIR.iterdir()))"], cwd=elsewhere).stdout.splitlines()
    assert str(REPO_ROOT) not in where[0] and "/env/" in where[0]
    assert "experiment" in where[1] and "config.yaml" in where[1]
    version = _run([python.parent / "codesign", "--version"], cwd=elsewhere).stdout
    assert version.startswith("codesign ") and version.split()[1][0].isdigit()


@pytest.mark.parametrize("experiment", ["psf", "simulate", "evaluate"])
def test_the_wheel_runs_the_smoke_experiments_from_any_folder(installed, experiment):
    python, elsewhere = installed
    run_dir = elsewhere / "runs" / experiment
    extra = ["checkpoint=pretrained", "evaluate.max_scenes=2", "evaluate.laser_strengths=[1e6]"] \
        if experiment == "evaluate" else []
    _run([python, "-m", "codesign", f"+experiment={experiment}", "debug=smoke", "logging.tensorboard=false",
          f"hydra.run.dir={run_dir}", *extra], cwd=elsewhere)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics  # the run wrote its figures
    if experiment == "evaluate":
        assert metrics["steps"] > 0 and "laser_1e6" in metrics["evaluation"]
