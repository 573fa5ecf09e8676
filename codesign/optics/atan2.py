"""atan of a ratio without the division (the printed phase convention of Eq. PhaseFunc)."""
from __future__ import annotations

import torch


def atan_of_ratio(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """atan(y / x) in [-pi/2, pi/2] as atan2(y * sign(x), |x|), sign(0) = +1.

    Dividing first gives inf at x = 0 and a 0 * inf = NaN gradient; this form stays finite there (torch.atan2's
    own gradient is 0 at the origin, checked in tests/optics/test_metrics.py).
    """
    s = torch.where(x >= 0, torch.ones_like(x), -torch.ones_like(x))
    return torch.atan2(y * s, x * s)
