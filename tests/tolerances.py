"""Floating-point comparisons stated in units of the values' rounding: a tolerance in ulps (units in the last place)
holds on every CPU's vector code, where an absolute tolerance below one ulp of the compared values holds only on the
CPU it was tuned on."""
from __future__ import annotations

import numpy as np
import torch


def spacing(values: torch.Tensor) -> torch.Tensor:
    """One ulp of each value: the distance from |value| to the next representable number of its dtype."""
    mag = values.abs()
    return torch.nextafter(mag, torch.full_like(mag, float("inf"))) - mag


def assert_within_ulps(actual, expected, ulps: float, scale: float | None = None) -> None:
    """Every ``|actual - expected|`` at most ``ulps`` ulps: of each expected value, or, with ``scale``, of a value of
    that magnitude (an operation whose rounding error follows its largest terms, not its result: a sum, a
    recurrence, an average of terms of order ``scale``). Tensors or arrays of the same floating dtype."""
    a = torch.as_tensor(np.asarray(actual) if not torch.is_tensor(actual) else actual).detach()
    e = torch.as_tensor(np.asarray(expected) if not torch.is_tensor(expected) else expected).detach()
    assert a.shape == e.shape, f"shapes differ: {tuple(a.shape)} and {tuple(e.shape)}"
    assert a.dtype == e.dtype and e.is_floating_point(), f"dtypes: {a.dtype} and {e.dtype} (floating, the same)"
    unit = spacing(e) if scale is None else spacing(torch.tensor(float(scale), dtype=e.dtype)).expand_as(e)
    diff = (a - e).abs()
    within = diff <= ulps * unit
    if not bool(within.all()):
        worst = int(torch.argmax(torch.where(within, torch.zeros_like(diff), diff / unit)))
        raise AssertionError(
            f"{int((~within).sum())} of {e.numel()} values differ by more than {ulps} ulp(s); worst at flat index "
            f"{worst}: {float(a.reshape(-1)[worst])!r} against {float(e.reshape(-1)[worst])!r}, "
            f"{float(diff.reshape(-1)[worst] / unit.reshape(-1)[worst]):.3g} ulps")
