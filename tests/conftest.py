"""Shared fixtures and the --runslow switch for the codesign test suite."""
from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

from codesign.config import resolvers

REPO_ROOT = Path(__file__).resolve().parent.parent

# CODESIGN_TEST_THREADS=1 when the machine is shared (two torch processes on 2 cores slow each other 5-20x).
torch.set_num_threads(int(os.environ.get("CODESIGN_TEST_THREADS", "2")))
resolvers.register()  # conf/config.yaml's ${codesign_stamp:} etc., for tests that compose with the Hydra API


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False, help="also run tests marked slow")
    parser.addoption("--device", default="cpu",
                     help="torch device of the device tests (tests/device/): cpu (default) or cuda / cuda:N")


def pytest_configure(config):
    name = config.getoption("--device")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise pytest.UsageError(f"--device {name!r}: not a torch device; allowed: cpu, cuda, cuda:N") from None
    if dev.type not in ("cpu", "cuda"):
        raise pytest.UsageError(f"--device {name!r}: allowed: cpu, cuda, cuda:N")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise pytest.UsageError(f"--device {name}: torch {torch.__version__} sees no CUDA device "
                                "(torch.cuda.is_available() is False)")
    if dev.type == "cuda" and (dev.index or 0) >= torch.cuda.device_count():
        raise pytest.UsageError(f"--device {name}: only {torch.cuda.device_count()} CUDA device(s) visible")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    skip_slow = pytest.mark.skip(reason="slow: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip_slow)


@pytest.fixture(scope="session")
def device(request) -> torch.device:
    """The device of the device tests: ``--device`` (default cpu)."""
    dev = torch.device(request.config.getoption("--device"))
    return torch.device("cuda", torch.cuda.current_device()) if dev.type == "cuda" and dev.index is None else dev


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The repository root (holds codesign/ and conf/)."""
    return REPO_ROOT


@pytest.fixture(scope="session")
def small_spec():
    """64 pupil samples across the aperture, 64 x 64 focal window at the sensor pitch (MFT)."""
    from codesign.optics import OpticsSpec

    return OpticsSpec.with_samples_across(64, focal_n=64)


@pytest.fixture(scope="session")
def small_system64(small_spec):
    """float64 optical system on ``small_spec``."""
    from codesign.optics import OpticalSystem

    return OpticalSystem(small_spec, dtype=torch.float64)


@pytest.fixture(scope="session")
def tiny_spec():
    """A very small valid spec for gradchecks: 24 samples across the aperture, 32 x 32 focal window."""
    from codesign.optics import OpticsSpec

    return OpticsSpec.with_samples_across(24, focal_n=32)


@pytest.fixture(scope="session")
def tiny_system64(tiny_spec):
    from codesign.optics import OpticalSystem

    return OpticalSystem(tiny_spec, dtype=torch.float64)
