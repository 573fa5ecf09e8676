"""Model tests run on one intra-op thread."""
from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    """These networks are tiny: one intra-op thread is as fast and avoids OpenMP spin-waits on a busy 2-core box."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
