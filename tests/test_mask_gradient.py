"""benchmarks/mask_gradient.py: the signal-to-noise statistics of per-batch gradients, against closed forms."""
from __future__ import annotations

import math

import pytest
import torch

from benchmarks.mask_gradient import main, statistics


def test_two_batches_closed_form():
    # mean (2, 0); each batch 1 from it: noise^2 = (1 + 1) / (2 - 1) = 2; signal^2 = 4 - 2 / 2 = 3
    res = statistics(torch.tensor([[1.0, 0.0], [3.0, 0.0]], dtype=torch.float64), ["a", "b"])
    assert res["batch_noise_rms"] == pytest.approx(math.sqrt(2))
    assert res["mean_gradient_norm"] == pytest.approx(math.sqrt(3))
    assert res["snr_one_batch"] == pytest.approx(math.sqrt(1.5))
    assert res["mean_pairwise_cosine"] == pytest.approx(1.0)
    assert (res["batches_for_snr_1"], res["batches_for_snr_3"]) == (1, 6)
    assert res["per_parameter"]["a"] == pytest.approx({"mean": 2.0, "std": math.sqrt(2), "snr": math.sqrt(2)})


def test_pure_noise_has_no_signal_and_opposite_batches_cosine_minus_one():
    res = statistics(torch.tensor([[1.0, 1.0], [-1.0, -1.0]], dtype=torch.float64), ["a", "b"])
    assert res["mean_gradient_norm"] == 0.0 and res["snr_one_batch"] == 0.0
    assert res["mean_pairwise_cosine"] == pytest.approx(-1.0) and res["batches_for_snr_1"] is None


def test_a_large_sample_recovers_the_snr():
    gen = torch.Generator().manual_seed(0)
    mu = torch.tensor([3.0, 4.0], dtype=torch.float64)  # |mu| = 5; per-component noise 5: RMS noise 5 sqrt(2)
    g = mu + 5.0 * torch.randn(20000, 2, generator=gen, dtype=torch.float64)
    res = statistics(g, ["a", "b"])
    assert res["snr_one_batch"] == pytest.approx(1 / math.sqrt(2), rel=0.03)


def test_one_batch_is_refused(capsys):
    with pytest.raises(SystemExit):
        main(["--checkpoint", "x.pt", "--batches", "1"])
    assert "--batches 1: at least 2 (the noise needs two batches)" in capsys.readouterr().err
