"""The joint run's printed summary: the paired per-scene noise estimate and the verdict's wording."""
from __future__ import annotations

import math

import pytest

from codesign.train.summary import joint_summary, paired_difference, verdict


def _metrics(learned: list[float], published: list[float], lsr: float = 4e-3) -> dict:
    def table(v):
        return {c: {"sgan": {"psnr_matched": v}, "sensor": {"psnr_matched": v - 1}, "wiener": {"psnr_matched": v - 2}}
                for c in ("laser_0", "laser_1e3", "laser_1e6")}

    return {"lsr": lsr, "lsr_published": 8e-3, "mtf_mean": 0.04, "mtf_mean_published": 0.043, "lsr_over_limit": 6.0,
            "lsr_over_limit_published": 12.0, "steps": 160, "seed": 3, "evaluation_scenes": ["a"] * len(learned),
            "evaluation": table(sum(learned) / len(learned)),
            "evaluation_published": table(sum(published) / len(published)),
            "evaluation_per_scene_psnr_matched": {"laser_1e6": {"sgan": learned}},
            "evaluation_per_scene_psnr_matched_published": {"laser_1e6": {"sgan": published}}}


def test_paired_difference_is_the_mean_and_its_95_percent_t_interval():
    mean, noise = paired_difference([21.0, 22.0, 26.0], [20.0, 20.0, 20.0])  # differences 1, 2, 6
    assert mean == pytest.approx(3.0)
    t_975_2 = 4.302652729911275  # Student's t, 97.5 % quantile, 2 degrees of freedom
    assert noise == pytest.approx(t_975_2 * math.sqrt(((1 - 3) ** 2 + (2 - 3) ** 2 + (6 - 3) ** 2) / 2) / math.sqrt(3))
    _, two = paired_difference([21.0, 19.0], [20.0, 20.0])  # 1 degree of freedom: t = 12.706, sd 1.414, se 1
    assert two == pytest.approx(12.706204736174698)
    assert paired_difference([21.0], [20.0]) == (1.0, None)


def test_verdict_within_noise_and_real():
    noisy = verdict(_metrics([21.0, 19.2], [20.0, 20.0]), "sgan")  # +0.1 +- 11.4
    assert noisy.endswith("within noise") and "+0.10 dB" in noisy and "50% less laser light" in noisy
    real = verdict(_metrics([21.0, 21.2, 21.1], [20.0, 20.1, 20.0]), "sgan")  # +1.07 +- 0.14
    assert "+1.07 dB" in real and "+-0.14 dB): beyond the scene noise (one seed" in real
    one = verdict(_metrics([21.0], [20.0], lsr=9.2e-3), "sgan")
    assert "15% more laser light" in one and "no noise estimate" in one


def test_summary_lists_both_masks_the_floors_and_the_verdict():
    text = joint_summary(_metrics([21.0, 19.2], [20.0, 20.0]), "sgan")
    lines = text.splitlines()
    assert lines[0] == "== summary: 160 steps, seed 3, 2 held-out test scene(s) =="
    assert lines[2].split() == ["learned", "4.000e-03", "0.0400", "6.00"]
    assert lines[3].split() == ["published", "8.000e-03", "0.0430", "12.00"]
    assert lines[5].split()[-3:] == ["20.10", "20.10", "20.10"] and lines[7].split()[-1] == "19.00"
    assert lines[-1].startswith("verdict:")
