"""``--device``: a device the machine does not have, or no device at all, stops pytest before any test, named."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[2]


def _pytest(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "tests/device/test_device_option.py", *args],
                          capture_output=True, text=True, cwd=REPO)


def test_a_name_that_is_no_device_is_a_usage_error():
    out = _pytest("--device", "tpu", "--collect-only")
    assert out.returncode == 4 and "--device 'tpu': not a torch device; allowed: cpu, cuda, cuda:N" in out.stderr


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_cuda_without_a_gpu_is_a_usage_error():
    """In process: conftest's check on a configuration asking for cuda (the exit-code path: the test above)."""
    from tests.conftest import pytest_configure

    class Config:
        def getoption(self, name):
            return "cuda"

    with pytest.raises(pytest.UsageError, match="^" + re.escape(f"--device cuda: torch {torch.__version__} sees no "
                                                                    "CUDA device")):
        pytest_configure(Config())
