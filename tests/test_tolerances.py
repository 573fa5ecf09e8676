"""The ulp comparison the suite's floating-point tests use (tests/tolerances.py) holds what it says."""
from __future__ import annotations

import pytest
import torch

from tests.tolerances import assert_within_ulps, spacing


def _up(x: torch.Tensor, k: int) -> torch.Tensor:
    for _ in range(k):
        x = torch.nextafter(x, torch.full_like(x, float("inf")))
    return x


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ulps_are_counted_per_value_and_refused_past_the_bound(dtype):
    e = torch.tensor([1e-20, 0.1, 1.0, 3.0, 1e20], dtype=dtype)
    assert torch.equal(spacing(e), _up(e, 1) - e)
    assert_within_ulps(_up(e, 2), e, 2)
    with pytest.raises(AssertionError, match=r"^5 of 5 values differ by more than 2 ulp\(s\); worst at flat index "
                                             r"\d: .* 3 ulps$"):
        assert_within_ulps(_up(e, 3), e, 2)


def test_a_scale_states_the_rounding_of_the_terms_not_of_the_result():
    e = torch.tensor([0.0, 1e-17], dtype=torch.float64)
    a = e + 2.2e-16  # one ulp of a term of order 1, far above the ulp of the result
    with pytest.raises(AssertionError):
        assert_within_ulps(a, e, 2)
    assert_within_ulps(a, e, 1, scale=1.0)
