"""Run ``python -m codesign ...`` in a subprocess from the repository root, as a user would."""
from __future__ import annotations

import os
import subprocess
import sys

from tests.conftest import REPO_ROOT


def run_codesign(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "2", "MKL_NUM_THREADS": "2"}
    return subprocess.run([sys.executable, "-m", "codesign", *args], cwd=REPO_ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout)
