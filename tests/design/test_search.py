"""+experiment=mask_search: the nlopt objective and its gradients, the search itself, settings and floor checks,
failure reporting, mask.init=PATH, and an end-to-end smoke run through the CLI."""
from __future__ import annotations

import json
import logging
import math

import nlopt
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from codesign.design.search import CONSTRAINED, MaskObjective, run_start
from codesign.design.search_spec import SearchSpec
from codesign.tasks.mask_search import run as run_mask_search
from codesign.errors import ConfigError
from codesign.optics import OpticalSystem, OpticsSpec, RadialMTF, build_mask, metrics
from codesign.optics.masks import HalfRingMask
from tests.cli import run_codesign
from tests.conftest import REPO_ROOT

# 64 pupil samples across the aperture, 128 x 128 window (rings up to r ~ 19 lambda f / W_a fit): ~10 ms/evaluation
TINY = {"pupil_pitch_m": 6.0e-5, "focal_n": 128}
TINY_CLI = [f"optics.{k}={v}" for k, v in TINY.items()] + ["search.r_bounds=[0.5,18]", "logging.tensorboard=false"]
ALLOWED = ", ".join(CONSTRAINED)
LO = np.array([0.5] * 5 + [0.0] * 5)
HI = np.array([18.0] * 5 + [2 * math.pi] * 5)


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # the suite shares 2 cores; these checks are sized for one
    yield
    torch.set_num_threads(before)


def _system(dtype=torch.float32):
    spec = OpticsSpec(**TINY)
    return OpticalSystem(spec, dtype=dtype), RadialMTF(spec)


def _objective(x0, floor, dtype=torch.float32, on_eval=None):
    system, radial = _system(dtype)
    mask = HalfRingMask(system.grid, system.spec.aperture_diameter_m, x0[:5], x0[5:])
    return MaskObjective(system, mask, radial, (0.0, 0.5), 16.0, floor, on_eval)


def _cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=["+experiment=mask_search", *TINY_CLI, *overrides])


# ---- (a) the search improves a poor mask under the floor -------------------------------------------------------
def test_search_improves_poor_mask_and_keeps_floor():
    x0 = np.array([2.0] * 5 + [0.2, 1.4, 2.6, 3.8, 5.0])  # five equal rings: a poor half-ring mask
    start = _objective(x0, 1.0).compute(x0, False)
    floor = 0.9 * start.mtf_mean
    obj = _objective(x0, floor)
    res = run_start(obj, "0", x0, LO, HI, "LD_MMA", None, 40, 0, 1e-4, 1e-6)
    assert res["feasible"] and res["exception"] is None and res["result"] in ("MAXEVAL_REACHED", "XTOL_REACHED",
                                                                                 "FTOL_REACHED", "SUCCESS")
    assert res["evaluations"] == len(obj.records) <= 40
    assert res["lsr_smooth"] < 0.85 * start.lsr_smooth  # measured 0.096 from 0.129
    assert res["mtf_mean"] >= floor
    # the kept best is the lowest feasible evaluation, and the records agree with the floor
    feas = [ev for _, _, ev in obj.records if ev.feasible]
    assert all(ev.feasible == (ev.mtf_mean >= floor) for _, _, ev in obj.records)
    assert obj.best.lsr_smooth == min(ev.lsr_smooth for ev in feas) == res["lsr_smooth"]
    assert all((LO <= ev.x).all() and (ev.x <= HI).all() for _, _, ev in obj.records)


def test_derivative_free_and_global_with_polish():
    x0 = np.array([3.0, 7.0, 1.5, 5.0, 2.0, 1.9, 1.1, 1.2, 1.2, 1.2])
    obj = _objective(x0, 0.1)
    res = run_start(obj, "0", x0, LO, HI, "LN_COBYLA", None, 12, 0, 1e-4, 1e-6)
    assert res["evaluations"] == 12 and res["result"] == "MAXEVAL_REACHED"
    assert all(ev.grad_f is None for _, _, ev in obj.records)  # no backward pass without a gradient request
    res = run_start(obj, "1", x0, LO, HI, "GN_ISRES", "LD_MMA", 10, 6, 1e-4, 1e-6)
    assert res["polish"]["algorithm"] == "LD_MMA" and 0 < res["polish"]["evaluations"] <= 6
    assert res["evaluations"] == 10 + res["polish"]["evaluations"]


# ---- (b) the torch gradient fed to nlopt matches finite differences --------------------------------------------
def test_gradients_match_finite_differences():
    x = np.array([3.1, 7.4, 1.3, 5.2, 2.2, 1.9, 0.7, 2.5, 4.0, 5.6])
    obj = _objective(x, 0.05, torch.float64)
    gf, gc = np.zeros(10), np.zeros(10)
    f = obj.objective(x, gf)
    c = obj.constraint(x, gc)
    assert len(obj.records) == 1  # one evaluation answers both callbacks
    assert f == pytest.approx(math.log(obj.records[0][2].lsr_smooth))
    assert c == pytest.approx(math.log(0.05 / obj.records[0][2].mtf_mean))
    h, fd_f, fd_c = 1e-6, np.zeros(10), np.zeros(10)
    for i in range(10):
        e = np.zeros(10)
        e[i] = h
        p, m = obj.compute(x + e, False), obj.compute(x - e, False)
        fd_f[i], fd_c[i] = (p.f - m.f) / (2 * h), (p.c - m.c) / (2 * h)
    np.testing.assert_allclose(gf, fd_f, rtol=1e-5, atol=1e-7 * np.abs(fd_f).max())
    np.testing.assert_allclose(gc, fd_c, rtol=1e-5, atol=1e-7 * np.abs(fd_c).max())
    # float32 (the default precision) agrees to ~0.1%
    g32 = _objective(x, 0.05).compute(x, True)
    assert np.linalg.norm(g32.grad_f - gf) <= 5e-3 * np.linalg.norm(gf)
    assert np.linalg.norm(g32.grad_c - gc) <= 5e-3 * np.linalg.norm(gc)


# ---- (c) algorithm names and other settings ------------------------------------------------------------------
@pytest.mark.parametrize("key, value, message", [
    ("algorithm", "LD_FOO", f"search.algorithm = 'LD_FOO': not an nlopt algorithm; allowed: {ALLOWED}"),
    ("algorithm", "SUCCESS", f"search.algorithm = 'SUCCESS': not an nlopt algorithm; allowed: {ALLOWED}"),
    ("algorithm", "LD_LBFGS", "search.algorithm = 'LD_LBFGS': nlopt's LD_LBFGS cannot handle the inequality "
                              f"constraint mtf_mean >= floor; allowed: {ALLOWED}"),
    ("algorithm", "GN_CRS2_LM", "search.algorithm = 'GN_CRS2_LM': nlopt's GN_CRS2_LM cannot handle the inequality "
                                f"constraint mtf_mean >= floor; allowed: {ALLOWED}"),
    ("local_algorithm", "GN_ISRES", "search.local_algorithm = 'GN_ISRES': nlopt's GN_ISRES is a global algorithm; "
                                    "the polish needs a local one; allowed: LD_MMA, LD_CCSAQ, LD_SLSQP, LN_COBYLA"),
    ("local_algorithm", "LN_BOBYQA", "search.local_algorithm = 'LN_BOBYQA': nlopt's LN_BOBYQA cannot handle the "
                                     "inequality constraint mtf_mean >= floor; allowed: LD_MMA, LD_CCSAQ, LD_SLSQP, "
                                     "LN_COBYLA"),
])
def test_algorithm_names(key, value, message):
    with pytest.raises(ConfigError) as err:
        SearchSpec(**{key: value})
    assert str(err.value) == message


@pytest.mark.parametrize("changes, pattern", [
    ({"init": "best"}, r"^search\.init = 'best': must be one of published, random, mask$"),
    ({"mtf_floor": "paper"}, r"^search\.mtf_floor = 'paper': must be published .* or a number in \(0, 1\]"),
    ({"r_bounds": [5, 1]}, r"^search\.r_bounds = \[5, 1\]: must be \[low, high\] with low < high"),
    ({"r_bounds": [0, 10]}, r"^search\.r_bounds = \[0\.0, 10\.0\]: must be \[low, high\] with 0 < low"),
    ({"max_evals": 0}, r"^search\.max_evals = 0: must be an integer >= 1"),
    ({"pareto_factors": [1.0, -1]}, r"^search\.pareto_factors\[1\] = -1: must be a finite number > 0"),
    ({"mtf_band": [0.5, 1.5]}, r"^search\.mtf_band\[1\] = 1\.5: must be a finite number >= 0 and <= 1"),
])
def test_bad_settings(changes, pattern):
    with pytest.raises(ConfigError, match=pattern):
        SearchSpec(**changes)


def test_unknown_search_key_and_defaults():
    with pytest.raises(ConfigError, match=r"^search\.algoritm = 'LD_MMA': unknown key; allowed: algorithm, "):
        SearchSpec.from_config({"algoritm": "LD_MMA"})
    # the YAML defaults are valid and match the dataclass's
    s = SearchSpec.from_config(OmegaConf.to_container(_cfg().search, resolve=True))
    assert s == SearchSpec(r_bounds=(0.5, 18.0), theta_bounds=(0.0, 6.283185307))
    assert SearchSpec(pareto_factors=[]).pareto_factors is None


# ---- (d) impossible floors, and a search that finds nothing feasible -------------------------------------------
@pytest.mark.parametrize("overrides, pattern", [
    (["search.mtf_floor=0.9"], r"^search\.mtf_floor = 0\.9: gives the MTF floor 0\.9, at or above the uncoded "
                               r"aperture's mtf_mean 0\.6\d*, which no phase mask can reach: mtf_floor x factor must "
                               r"be below 0\.6\d* \(the published mask's mtf_mean is 0\.0\d*\)$"),
    (["search.mtf_floor_factor=20"], r"^search\.mtf_floor_factor = 20(\.0)?: gives the MTF floor"),
    (["search.pareto_factors=[1.0,30]"], r"^search\.pareto_factors\[1\] = 30(\.0)?: gives the MTF floor"),
    (["mask=freeform"], r"^mask\.kind = 'freeform': mask_search optimizes the radii and angles of a half-ring"),
])
def test_impossible_settings_are_config_errors(tmp_path, overrides, pattern):
    with pytest.raises(ConfigError, match=pattern):
        run_mask_search(_cfg(*overrides), tmp_path, torch.device("cpu"))
    assert not list(tmp_path.iterdir())  # refused before any work or output


def test_infeasible_in_practice_ends_cleanly(tmp_path, caplog):
    cfg = _cfg("search.mtf_floor=0.6", "search.max_evals=3", "search.starts=1", "search.pareto_factors=null")
    with caplog.at_level(logging.ERROR, logger="codesign.mask_search"):
        lsr = run_mask_search(cfg, tmp_path, torch.device("cpu"))
    assert math.isnan(lsr)
    assert any(r.levelno == logging.ERROR and "NO FEASIBLE POINT" in r.getMessage() for r in caplog.records)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["feasible"] is False and m["evaluations"] == 3
    assert 0 < m["min_violation"] == pytest.approx(0.6 - m["mtf_mean"], rel=1e-6)
    assert m["starts"][0]["feasible"] is False and m["starts"][0]["min_violation"] > 0
    best = json.loads((tmp_path / "best_mask.json").read_text())
    assert best["feasible"] is False
    for name in ("evaluations.csv", "phase.png", "mtf.png", "pareto.png"):
        assert (tmp_path / name).is_file(), name


# ---- nlopt stops are reported, our own errors are not swallowed ------------------------------------------------
def test_forced_stop_is_recorded_and_best_kept():
    def stop_after_5(obj, ev):
        if len(obj.records) == 5:
            raise nlopt.ForcedStop("enough")

    x0 = np.array([3.0, 7.0, 1.5, 5.0, 2.0, 1.9, 1.1, 1.2, 1.2, 1.2])
    obj = _objective(x0, 0.01, on_eval=stop_after_5)
    res = run_start(obj, "0", x0, LO, HI, "LD_MMA", None, 50, 0, 1e-4, 1e-6)
    assert res["result"] == "FORCED_STOP" and res["exception"] == "ForcedStop: enough"
    assert res["evaluations"] == 5 and res["feasible"]
    assert res["lsr_smooth"] == min(ev.lsr_smooth for _, _, ev in obj.records if ev.feasible)


def test_evaluation_errors_propagate():
    def broken(obj, ev):
        raise RuntimeError("a bug in the callback")

    x0 = np.array([3.0, 7.0, 1.5, 5.0, 2.0, 1.9, 1.1, 1.2, 1.2, 1.2])
    with pytest.raises(RuntimeError, match="a bug in the callback"):
        run_start(_objective(x0, 0.01, on_eval=broken), "0", x0, LO, HI, "LD_MMA", None, 5, 0, 1e-4, 1e-6)


# ---- (f) end to end through the CLI, and (e) mask.init=PATH from its best_mask.json -----------------------------
OUTPUTS = ["evaluations.csv", "best_mask.json", "metrics.json", "phase.png", "psf_log.png", "mtf.png",
           "published_phase.png", "published_psf_log.png", "pareto.png"]


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("mask_search") / "run"
    proc = run_codesign("+experiment=mask_search", "debug=smoke", "threads=1", f"hydra.run.dir={run_dir}")
    assert proc.returncode == 0, proc.stderr[-4000:]
    return run_dir, proc.stdout + proc.stderr


def test_smoke_run_writes_everything(smoke_run):
    run_dir, out = smoke_run
    for name in OUTPUTS:
        assert (run_dir / name).is_file() and (run_dir / name).stat().st_size > 0, name
    assert list(run_dir.glob("events.out.tfevents.*"))
    assert not [p.name for p in run_dir.iterdir() if p.name.endswith(".tmp")]
    m = json.loads((run_dir / "metrics.json").read_text())
    for k in ("lsr", "lsr_smooth", "lsr_sampled", "mtf_mean", "mtf_min", "lsr_baseline", "mtf_mean_baseline",
              "mtf_floor", "r_1", "r_5", "theta_1", "theta_5", "evaluations", "seconds", "evals_per_second"):
        assert isinstance(m[k], (int, float)) and math.isfinite(m[k]), k
    assert m["algorithm"] == "LN_COBYLA" and m["feasible"] is True and m["evaluations"] == 16  # 2 starts x 8
    assert m["mtf_mean"] >= m["mtf_floor"] == pytest.approx(m["mtf_mean_baseline"])
    assert m["lsr_smooth"] <= m["lsr_smooth_baseline"]  # start 0 is the published mask itself
    assert [s["start"] for s in m["starts"]] == ["0", "1"] and m["starts"][0]["init"] == "published"
    assert [p["factor"] for p in m["pareto"]] == [1.0]
    rows = (run_dir / "evaluations.csv").read_text().splitlines()
    assert rows[0].split(",")[:5] == ["floor_factor", "mtf_floor", "start", "eval", "r_1"] and len(rows) == 17
    assert "best feasible" in out or "MAXEVAL_REACHED" in out


def test_mask_init_round_trip(smoke_run, tmp_path):
    run_dir, _ = smoke_run
    best = json.loads((run_dir / "best_mask.json").read_text())
    spec = OpticsSpec(pupil_pitch_m=2.0e-5, focal_n=160)  # the smoke optics the run used
    system = OpticalSystem(spec)
    path = str(run_dir / "best_mask.json")
    mask = build_mask({"kind": "halfring", "preset": "published", "init": path}, system.grid,
                      spec.aperture_diameter_m)  # init wins over preset
    assert mask.r.tolist() == best["r"] and mask.theta.tolist() == best["theta"]
    with torch.no_grad():
        phase = mask.phase()
        psf = system.psf(phase)
        assert system.refined_peak(phase, psf) / system.uncoded_peak == pytest.approx(best["lsr"], rel=1e-6)
        assert float(metrics.lsr_smooth(psf, system.uncoded_peak, 16)) == pytest.approx(best["lsr_smooth"], rel=1e-6)
    free = build_mask({"kind": "freeform", "basis": "pixel", "init": path}, system.grid, spec.aperture_diameter_m)
    torch.testing.assert_close(free.phase().detach(), phase, rtol=0, atol=1e-6)


@pytest.mark.parametrize("content, pattern", [
    (None, r"^mask\.init = '.*missing\.json': must be null or the path of a mask record \(best_mask\.json of "
           r"\+experiment=mask_search, learned_mask\.json of joint, mask\.json of psf\); no such file$"),
    ("{not json", r"; cannot be read as JSON \(Expecting property name"),
    ('{"kind": "freeform", "r": [1], "theta": [1]}', r"; the file holds kind 'freeform', not a mask family "
                                                     r"\(halfring, pixel, spiral, zernike\)$"),
    ('{"kind": "halfring", "r": [1, 2], "theta": [1]}', r"; its r and theta must be non-empty lists of numbers "
                                                        r"of equal length \(got \[1, 2\] and \[1\]\)$"),
    ('{"kind": "halfring", "r": ["a"], "theta": [1]}', r"; its r and theta must be non-empty lists of numbers"),
])
def test_mask_init_bad_files(tmp_path, content, pattern):
    path = tmp_path / ("missing.json" if content is None else "best_mask.json")
    if content is not None:
        path.write_text(content)
    system, _ = _system()
    with pytest.raises(ConfigError, match=pattern):
        build_mask({"kind": "halfring", "init": str(path)}, system.grid, 3.83e-3)


def test_mask_init_conflicts_and_freeform_choices(tmp_path):
    path = tmp_path / "best_mask.json"
    path.write_text('{"kind": "halfring", "r": [1.0, 2.0], "theta": [0.5, 1.5]}')
    system, _ = _system()
    with pytest.raises(ConfigError, match=r"^mask\.init = .*: cannot be combined with explicit mask\.r / mask\.theta"):
        build_mask({"kind": "halfring", "init": str(path), "r": [1.0], "theta": [1.0]}, system.grid, 3.83e-3)
    mask = build_mask({"kind": "halfring", "preset": None, "init": str(path)}, system.grid, 3.83e-3)
    assert mask.r.tolist() == [1.0, 2.0]
    with pytest.raises(ConfigError, match=r"^mask\.init = 'nope': must be one of published, zero, defocus or the path "
                                          r"of a mask record \(best_mask\.json of \+experiment=mask_search, "
                                          r"learned_mask\.json of joint, mask\.json of psf\); no such file$"):
        build_mask({"kind": "freeform", "init": "nope"}, system.grid, 3.83e-3)


def test_search_starts_from_mask_init(tmp_path):
    path = tmp_path / "seed.json"
    path.write_text('{"kind": "halfring", "r": [3.0, 7.0, 1.5, 5.0, 2.0], "theta": [1.9, 1.1, 1.2, 1.2, 1.2]}')
    cfg = _cfg(f"mask.init={path}", "search.init=mask", "search.max_evals=2", "search.starts=1",
               "search.pareto_factors=null", "search.mtf_floor=0.01")
    assert cfg.mask.init == str(path)  # the key exists in conf/mask/halfring.yaml: no + needed
    run_mask_search(cfg, tmp_path / "run", torch.device("cpu"))
    first = (tmp_path / "run" / "evaluations.csv").read_text().splitlines()[1].split(",")
    np.testing.assert_allclose([float(v) for v in first[4:14]], [3.0, 7.0, 1.5, 5.0, 2.0, 1.9, 1.1, 1.2, 1.2, 1.2],
                               rtol=1e-6)


# ---- the window-energy floor: the search may not push the PSF out of the optics window ---------------------
def test_energy_floor_is_enforced_and_its_gradient_matches_finite_differences():
    x = np.array([3.1, 7.4, 1.3, 5.2, 2.2, 1.9, 0.7, 2.5, 4.0, 5.6])
    system, radial = _system(torch.float64)
    mask = HalfRingMask(system.grid, system.spec.aperture_diameter_m, x[:5], x[5:])
    with torch.no_grad():
        energy0 = float(system.psf(mask.phase()).sum())
    obj = MaskObjective(system, mask, radial, (0.0, 0.5), 16.0, 0.01, None, energy_floor=0.99 * energy0)
    ev = obj.compute(x, True)
    assert ev.energy == pytest.approx(energy0, rel=1e-12) and ev.energy_ok
    assert ev.e == pytest.approx(math.log(0.99), rel=1e-9)
    h = 1e-6
    for i in (0, 3, 7):
        dx = np.zeros_like(x)
        dx[i] = h
        fd = (obj.compute(x + dx, False).e - obj.compute(x - dx, False).e) / (2 * h)
        assert ev.grad_e[i] == pytest.approx(fd, rel=1e-4, abs=1e-8)
    # a floor above what the rings keep in the window: no point of a short search is feasible
    strict = MaskObjective(system, mask, radial, (0.0, 0.5), 16.0, 0.01, None, energy_floor=min(1.0, 1.5 * energy0))
    res = run_start(strict, "0", x, LO, HI, "LN_COBYLA", None, 10, 0, 1e-4, 1e-6)
    assert not res["feasible"] and all(not ev.energy_ok and not ev.feasible for _, _, ev in strict.records)


def test_energy_floor_setting_is_validated():
    with pytest.raises(ConfigError, match=r"search.energy_floor = 1.5: must be published"):
        SearchSpec.from_config({"energy_floor": 1.5})
    assert SearchSpec.from_config({"energy_floor": None}).energy_floor_value(0.8) is None
    assert SearchSpec.from_config({}).energy_floor_value(0.8) == 0.8
