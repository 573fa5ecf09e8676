"""Scene-parameter sampling (Sec. 6.2), fixed values and the evaluation presets of the paper."""
from __future__ import annotations

import json

import pytest
import torch

from codesign.data import (FIGURE_VALUES, LASER_STRENGTHS, PRESETS, ROBUSTNESS_STAGES, ParamConfig, SceneParams,
                           fixed_scene_params, preset_names, preset_params, sample_scene_params)
from codesign.errors import ConfigError

# Table 1: f = 0.11 m; the 2532 x 2532 laboratory crop at 5.4 um, and a non-square sensor to tell axes apart.
F_M = 0.11
W_M = 3352 * 5.4e-6
H_M = 2532 * 5.4e-6
N = 20_000


def _sample(seed: int = 0, batch: int = N, cfg=None, **kw) -> SceneParams:
    return sample_scene_params(batch, torch.Generator().manual_seed(seed), ParamConfig.from_config(cfg), W_M, H_M,
                               F_M, **kw)


@pytest.fixture(scope="module")
def big() -> SceneParams:
    return _sample(seed=123, dtype=torch.float64)


def test_shapes_dtype_and_api():
    p = _sample(batch=5)
    assert p.batch_size == len(p) == 5
    assert p.alpha_l.shape == (5,) and p.laser_angle_rad.shape == (5, 2)
    assert p.alpha_l.dtype == torch.float32 and p.alpha_l.device.type == "cpu"
    q = p.to("cpu", torch.float64)
    assert q.exposure_s.dtype == torch.float64 and torch.equal(q.alpha_b.float(), p.alpha_b)
    one = p.index(3)
    assert one.batch_size == 1 and one.laser_angle_rad.shape == (1, 2)
    assert one.c1.item() == p.c1[3].item() and p.index(-1).c2.item() == p.c2[4].item()
    with pytest.raises(IndexError):
        p.index(5)
    d = p.as_dict()
    json.dumps(d)  # metrics.json-ready
    assert set(d) == {"alpha_l", "alpha_b", "laser_angle_rad", "c1", "c2", "dark_current_mean_e",
                      "read_noise_mean_e", "read_noise_std_e", "exposure_s"}
    assert len(d["alpha_l"]) == 5 and len(d["laser_angle_rad"][0]) == 2
    r = p.replace(alpha_l=1e6, laser_angle_rad=(0.01, -0.02))
    assert torch.all(r.alpha_l == 1e6) and torch.equal(r.c1, p.c1)
    assert r.laser_angle_rad[2].tolist() == pytest.approx([0.01, -0.02])
    with pytest.raises(ValueError):
        SceneParams(**{**{k: getattr(p, k) for k in d}, "c1": torch.zeros(4)})


def test_alpha_l_on_the_10k_grid(big):
    grid = torch.linspace(0.0, 2.0e6, 10_000, dtype=torch.float64)
    assert torch.isin(big.alpha_l, grid).all()
    assert big.alpha_l.min() >= 0 and big.alpha_l.max() <= 2.0e6
    assert big.alpha_l.unique().numel() > 8_000  # ~8,650 distinct values expected from 20k draws of 10k
    assert big.alpha_l.mean().item() == pytest.approx(1.0e6, rel=0.02)  # std err ~0.4 %
    # float32 output keeps the grid too (same cast)
    assert torch.isin(_sample(seed=1, batch=1000).alpha_l, grid.float()).all()


def test_incidence_angle_three_sigma(big):
    sigma = big.laser_angle_rad.std(dim=0)
    assert sigma[0].item() == pytest.approx(0.12 * W_M / F_M, rel=0.03)
    assert sigma[1].item() == pytest.approx(0.12 * H_M / F_M, rel=0.03)
    assert big.laser_angle_rad.mean(dim=0).abs().max().item() < 0.05 * sigma.min().item()
    # the focal-plane footprint f * angle stays within +-0.36 of the sensor side for ~99.7 % of draws
    inside = (big.laser_angle_rad[:, 0] * F_M).abs() <= 0.36 * W_M
    assert inside.double().mean().item() == pytest.approx(0.9973, abs=0.002)


def test_noise_exposure_and_strength_moments(big):
    assert big.exposure_s.mean().item() == pytest.approx(0.1, rel=0.005)
    assert big.exposure_s.std().item() == pytest.approx(0.01, rel=0.03)
    assert big.exposure_s.min().item() >= 1e-4
    assert big.dark_current_mean_e.min().item() >= 0
    assert big.dark_current_mean_e.mean().item() == pytest.approx(0.002, rel=0.03)
    assert big.dark_current_mean_e.std().item() == pytest.approx(0.001, rel=0.06)  # clipping trims it a bit
    for name, lo, hi in [("read_noise_mean_e", 350, 400), ("read_noise_std_e", 10, 11), ("c1", 0, 0.25),
                         ("c2", 0.9, 1.1), ("alpha_b", 0.3, 0.7)]:
        t = getattr(big, name)
        span = hi - lo
        assert t.min().item() >= lo and t.max().item() <= hi, name
        assert t.min().item() < lo + 0.001 * span and t.max().item() > hi - 0.001 * span, name  # fills it
        assert t.mean().item() == pytest.approx((lo + hi) / 2, abs=0.01 * span), name


def test_reproducible_per_seed():
    a, b, c = _sample(seed=7, batch=64), _sample(seed=7, batch=64), _sample(seed=8, batch=64)
    for k, v in a.as_dict().items():
        assert v == b.as_dict()[k], k
        assert v != c.as_dict()[k], k


def test_config_ranges_are_used():
    p = _sample(batch=2000, cfg={"params": {"alpha_b_range": [0.5, 0.5], "c1_range": [0.1, 0.2],
                                            "alpha_l_range": [0, 10], "alpha_l_levels": 11,
                                            "exposure_std_s": 0.0}})
    assert torch.all(p.alpha_b == 0.5) and p.exposure_s.tolist() == pytest.approx([0.1] * 2000)
    assert set(p.alpha_l.tolist()) == {float(v) for v in range(11)}
    assert p.c1.min() >= 0.1 and p.c1.max() <= 0.2
    from_config = ParamConfig.from_config
    assert from_config(None) == ParamConfig() == from_config({}) == from_config({"params": None})


def test_log_spacing_draws_from_zero_and_geometric_levels_up_to_the_range_end():
    from codesign.data.params import laser_strength_levels

    pc = ParamConfig.from_config({"alpha_l_range": [0, 1.0e6], "alpha_l_levels": 7, "alpha_l_spacing": "log"})
    levels = laser_strength_levels(pc)
    # 0, then 6 levels from 1 to 1e6: a constant ratio 10^(6/5)
    assert len(levels) == 7 and levels[0] == 0 and levels[1] == 1
    assert levels[-1].item() == pytest.approx(1.0e6, rel=1e-12)
    ratios = levels[2:] / levels[1:-1]
    assert torch.allclose(ratios, torch.full_like(ratios, 10 ** 1.2), rtol=1e-12)
    # a range that starts above 1 keeps its lower end and has no zero level
    high = laser_strength_levels(ParamConfig.from_config({"alpha_l_range": [1e3, 1e6], "alpha_l_levels": 4,
                                               "alpha_l_spacing": "log"}))
    assert high.tolist() == pytest.approx([1e3, 1e4, 1e5, 1e6], rel=1e-12)
    # the paper's default grid is unchanged: 10,000 evenly spaced levels over [0, 2e6]
    assert torch.equal(laser_strength_levels(ParamConfig()), torch.linspace(0, 2e6, 10_000, dtype=torch.float64))
    # the draws: every one a level; log puts ~2/3 of them at <= 1e4 where the linear grid puts 0.5 %
    cfg = {"params": {"alpha_l_spacing": "log"}}
    drawn = _sample(batch=N, cfg=cfg, dtype=torch.float64).alpha_l
    grid = laser_strength_levels(ParamConfig.from_config(cfg["params"]))
    assert torch.isin(drawn, grid).all()
    share = lambda a: float((a <= 1e4).double().mean())  # noqa: E731
    assert share(drawn) == pytest.approx(4 / 6.30103, abs=0.02)
    assert share(_sample(batch=N, dtype=torch.float64).alpha_l) == pytest.approx(0.005, abs=0.002)


def test_mixed_spacing_is_half_the_levels_of_each_grid():
    from codesign.data.params import laser_strength_levels

    mixed = laser_strength_levels(ParamConfig.from_config({"alpha_l_range": [0, 1.0e6], "alpha_l_levels": 9,
                                                "alpha_l_spacing": "mixed"}))
    linear = torch.linspace(0, 1.0e6, 5, dtype=torch.float64)                    # the larger half: 5 levels
    log = laser_strength_levels(ParamConfig.from_config({"alpha_l_range": [0, 1.0e6], "alpha_l_levels": 4,
                                              "alpha_l_spacing": "log"}))        # 0, 1, 1e3, 1e6
    assert torch.equal(mixed, torch.sort(torch.cat([linear, log])).values)
    # a uniform draw over the default grid: a 50/50 mixture of the two grids' shares
    grid = laser_strength_levels(ParamConfig.from_config({"alpha_l_spacing": "mixed"}))
    assert len(grid) == 10_000 and torch.all(grid[1:] >= grid[:-1])
    assert float((grid <= 1e4).double().mean()) == pytest.approx(0.5 * 0.005 + 0.5 * 4 / 6.30103, abs=0.002)
    assert float((grid > 5e5).double().mean()) == pytest.approx(0.5 * 0.75 + 0.5 * 0.60103 / 6.30103, abs=0.002)


def test_bad_alpha_l_spacing_names_the_allowed_values():
    with pytest.raises(ConfigError, match=r"data\.params\.alpha_l_spacing.*must be one of linear, log, mixed"):
        ParamConfig.from_config({"alpha_l_spacing": "geometric"})
    with pytest.raises(ConfigError, match=r"data\.params\.alpha_l_range.*upper end must be >= 1"):
        ParamConfig.from_config({"alpha_l_spacing": "log", "alpha_l_range": [0, 0.5]})
    with pytest.raises(ConfigError, match=r"data\.params\.alpha_l_levels = 3: .* must be >= 4 \(both ends are "
                                          r"levels of each half\)"):
        ParamConfig.from_config({"alpha_l_spacing": "mixed", "alpha_l_levels": 3})


@pytest.mark.parametrize("key, value", [
    ("c1_range", [0.3, 0.1]), ("alpha_b_range", [-0.1, 0.5]), ("read_noise_std_range_e", "abc"),
    ("c2_range", [1.0]), ("alpha_l_levels", 0), ("alpha_l_levels", 2.5), ("exposure_mean_s", 0.0),
    ("exposure_min_s", 0), ("dark_current_mean_e", -0.002), ("angle_three_sigma_fraction", float("nan")),
    ("exposure_std_s", True), ("alpha_l_max", 2e6),
])
def test_bad_param_config_names_the_key(key, value):
    with pytest.raises(ConfigError) as e:
        _sample(batch=2, cfg={"params": {key: value}})
    assert e.value.key == f"data.params.{key}"
    assert f"data.params.{key}" in str(e.value)


def test_bad_call_arguments():
    with pytest.raises(ConfigError, match="batch"):
        _sample(batch=0)
    with pytest.raises(ConfigError, match="focal_length_m"):
        sample_scene_params(2, torch.Generator(), None, W_M, H_M, 0.0)
    with pytest.raises(TypeError):
        sample_scene_params(2, 0, None, W_M, H_M, F_M)
    with pytest.raises(ConfigError, match="params = .*must be a ParamConfig"):  # a spec, not the config block
        sample_scene_params(2, torch.Generator(), {"c1_range": [0, 1]}, W_M, H_M, F_M)


def test_fixed_scene_params_defaults_are_the_figure_settings():
    p = fixed_scene_params(3)
    assert p.batch_size == 3
    expected = {"alpha_l": 0.0, "alpha_b": 0.7, "c1": 0.20, "c2": 1.0, "dark_current_mean_e": 0.002,
                "read_noise_mean_e": 390.0, "read_noise_std_e": 10.5, "exposure_s": 0.1}
    assert {k: v for k, v in FIGURE_VALUES.items() if k != "laser_angle_rad"} == expected
    for k, v in expected.items():
        assert getattr(p, k).tolist() == pytest.approx([v] * 3), k
    assert torch.all(p.laser_angle_rad == 0)
    q = fixed_scene_params(2, alpha_l=1e6, laser_angle_rad=(0.001, 0.002), dtype=torch.float64)
    assert q.alpha_l.dtype == torch.float64 and q.alpha_l.tolist() == [1e6, 1e6]
    assert q.laser_angle_rad.tolist() == [[0.001, 0.002]] * 2
    with pytest.raises(ConfigError) as e:
        fixed_scene_params(1, alpha_x=1.0)
    assert e.value.key == "alpha_x" and "alpha_l" in e.value.allowed
    with pytest.raises(ConfigError) as e:
        fixed_scene_params(1, exposure_s=-1.0)
    assert e.value.key == "exposure_s"


def test_presets_hold_the_papers_values():
    assert LASER_STRENGTHS == (0.0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6)
    table = {  # supplement, tab:Degradation_modes
        "E1": (0.0, 0.8, 0.01), "E2": (3e4, 0.6, 0.03), "M": (3e5, 0.4, 0.05), "H1": (1e6, 0.3, 0.10),
        "H2": (1.5e6, 0.2, 0.20),
    }
    assert list(ROBUSTNESS_STAGES) == list(table)
    for name, (al, ab, c1) in table.items():
        assert ROBUSTNESS_STAGES[name] == {"alpha_l": al, "alpha_b": ab, "c1": c1}
        p = preset_params(name, 4, dtype=torch.float64)
        assert p.batch_size == 4
        assert p.alpha_l.tolist() == [al] * 4 and p.alpha_b.tolist() == [ab] * 4 and p.c1.tolist() == [c1] * 4
        assert p.c2.tolist() == [1.0] * 4 and p.read_noise_mean_e.tolist() == [390.0] * 4
        assert p.read_noise_std_e.tolist() == [10.5] * 4 and p.dark_current_mean_e.tolist() == [0.002] * 4
        assert p.exposure_s.tolist() == [0.1] * 4 and torch.all(p.laser_angle_rad == 0)
    fig = preset_params("figure", 1, dtype=torch.float64)
    assert {k: getattr(fig, k).item() for k in FIGURE_VALUES if k != "laser_angle_rad"} == \
        {k: v for k, v in FIGURE_VALUES.items() if k != "laser_angle_rad"}
    for v, name in zip(LASER_STRENGTHS, ["laser_0"] + [f"laser_1e{k}" for k in range(1, 7)]):
        assert preset_params(name, 1, dtype=torch.float64).alpha_l.item() == v
        assert PRESETS[name]["alpha_b"] == 0.7
    assert set(preset_names()) == set(PRESETS)


def test_unknown_preset_lists_allowed_names():
    with pytest.raises(ConfigError) as e:
        preset_params("E3", 1)
    assert e.value.value == "E3"
    for name in ("figure", "E1", "E2", "M", "H1", "H2", "laser_1e6"):
        assert name in e.value.allowed
