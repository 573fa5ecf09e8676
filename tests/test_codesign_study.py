"""The co-design study's bookkeeping (benchmarks/codesign_study.py): arms, held-out means, the seed statistics and
the significance rule, argument checks. The whole study at smoke size is opt-in (--runslow): ~2.5 min."""
from __future__ import annotations

import json

import pytest

from benchmarks import codesign_study as study


def _run(lsr: float, psnr: float) -> dict:
    return {"lsr": lsr, "net_psnr_matched_1e6": psnr}


def test_arms_for_a_design_and_their_folders(tmp_path):
    arms = study.arms({"spiral": (tmp_path / "rec.json", "spiral")})
    assert list(arms) == ["published (frozen)", "joint from published", "spiral (frozen)", "joint from spiral"]
    assert arms["published (frozen)"] == ["codesign.mask_lr=0"] and arms["joint from published"] == []
    assert arms["joint from spiral"] == ["mask=spiral", f"mask.init={tmp_path / 'rec.json'}", "codesign.lsr_max=start"]
    assert arms["spiral (frozen)"] == arms["joint from spiral"] + ["codesign.mask_lr=0"]
    assert [study.folder(a) for a in arms] == ["published_frozen", "joint_published", "spiral_frozen", "joint_spiral"]


def test_held_out_is_the_scene_weighted_mean_of_both_evaluations():
    def table(net: float, sensor: float, wiener: float) -> dict:
        row = lambda v: {"psnr": v, "ssim": v / 100, "psnr_matched": v + 1}  # noqa: E731
        return {f"laser_{a}": {"sgan": row(net), "sensor": row(sensor), "wiener": row(wiener)} for a in study.ALPHAS}

    builtin = {"evaluation": table(10.0, 20.0, 30.0), "evaluation_scenes": ["cell", "chelsea"]}
    photos = {"evaluation": table(16.0, 26.0, 36.0), "evaluation_scenes": [f"p{k}" for k in range(4)]}
    out = study.held_out(builtin, photos, study.network_column(builtin))
    assert out["scenes"] == 6
    assert out["net_psnr_0"] == pytest.approx((2 * 10 + 4 * 16) / 6)
    assert out["sensor_psnr_matched_1e3"] == pytest.approx((2 * 21 + 4 * 27) / 6)
    assert out["wiener_ssim_1e6"] == pytest.approx((2 * 0.30 + 4 * 0.36) / 6)


def test_network_column_is_the_one_that_is_not_a_floor():
    ev = {"evaluation": {"laser_0": {"sensor": {}, "wiener": {}, "g1_wiener": {}, "wiener_unet": {}}}}
    assert study.network_column(ev) == "wiener_unet"
    with pytest.raises(SystemExit, match="cannot tell the network's column"):
        study.network_column({"evaluation": {"laser_0": {"sensor": {}, "a": {}, "b": {}}}})


def test_gain_is_paired_by_seed_and_significant_only_beyond_twice_the_spread():
    ref = {0: _run(8e-3, 20.0), 1: _run(8e-3, 20.4), 2: _run(8e-3, 19.6)}  # std 0.4
    clear = {s: _run(2e-3, v["net_psnr_matched_1e6"] + 1.0) for s, v in ref.items()}  # +1.0 dB, std 0.4
    noisy = {0: _run(2e-3, 20.5), 1: _run(2e-3, 20.1), 2: _run(2e-3, 20.6)}  # +0.4 dB, within 2 x 0.4
    out = study.summarize({study.REFERENCE: ref, "clear": clear, "noisy": noisy})
    psnr = out["clear"]["net_psnr_matched_1e6"]
    assert psnr["mean"] == pytest.approx(21.0) and psnr["std"] == pytest.approx(0.4)
    assert psnr["gain"] == pytest.approx(1.0) and psnr["spread"] == pytest.approx(0.4) and psnr["significant"]
    assert psnr["gain_std"] == pytest.approx(0.0, abs=1e-12)  # the same +1.0 dB at every seed
    n = out["noisy"]["net_psnr_matched_1e6"]
    assert n["gain"] == pytest.approx(0.4) and n["spread"] == pytest.approx(0.4)  # the reference arm's, the larger
    assert n["significant"] is False
    assert "gain" not in out[study.REFERENCE]["lsr"] and out["clear"]["lsr"]["gain"] == pytest.approx(-6e-3)
    assert study.goal_met(out) == {"clear": True, "noisy": False}  # both at a quarter of the LSR


def test_joint_vs_frozen_pairs_each_joint_arm_with_its_own_frozen_arm():
    ref = {0: _run(8e-3, 20.0), 1: _run(8e-3, 20.4), 2: _run(8e-3, 19.6)}  # std 0.4
    frozen = {0: _run(2e-3, 24.0), 1: _run(2e-3, 24.1), 2: _run(2e-3, 23.9)}  # std 0.1
    joint = {s: _run(2e-3, v["net_psnr_matched_1e6"] + 0.6) for s, v in frozen.items()}  # +0.6 at every seed
    joint_pub = {s: _run(8e-3, v["net_psnr_matched_1e6"] + 0.6) for s, v in ref.items()}  # +0.6, spread 0.4
    out = study.joint_vs_frozen({study.REFERENCE: ref, "joint from published": joint_pub, "spline (frozen)": frozen,
                                 "joint from spline": joint})
    assert set(out) == {"published", "spline"}
    g = out["spline"]["1e6"]
    assert g["gain"] == pytest.approx(0.6) and g["spread"] == pytest.approx(0.1) and g["significant"]
    assert g["seeds"] == 3 and out["spline"]["goal_met"] is True
    p = out["published"]["1e6"]
    assert p["gain"] == pytest.approx(0.6) and p["spread"] == pytest.approx(0.4) and not p["significant"]
    assert out["published"]["goal_met"] is False


@pytest.mark.parametrize("argv, message", [
    (["--seeds", "3"], "--seeds: give at least 2 different seeds"),
    (["--steps", "0"], "--steps 0: must be >= 1"),
    (["--design", "x=/nonexistent.json"], "--design 'x=/nonexistent.json': no such record file"),
    (["--design", "nokind"], "--design 'nokind': must be NAME=RECORD"),
])
def test_bad_arguments_stop_before_any_run(argv, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as err:
        study.parse_args([*argv, "--scenes", str(tmp_path), "--out", str(tmp_path / "out")])
    assert err.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_record_that_is_not_a_mask_is_refused(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"lsr": 1}))
    with pytest.raises(SystemExit):
        study.parse_args(["--design", f"b={bad}", "--scenes", str(tmp_path)])
    assert "not a mask record (a JSON object with a 'kind')" in capsys.readouterr().err


@pytest.mark.slow
def test_the_whole_study_at_smoke_size(tmp_path, capsys):
    scenes = study.SCENES if study.SCENES.is_dir() else None
    if scenes is None:
        pytest.skip("the held-out photographs (../shared/data/scenes) are not on this machine")
    record = study.DESIGNS / "spiral" / "best_mask.json"
    assert study.main(["--smoke", "--seeds", "0", "1", "--design", f"spiral={record}", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "study.json").read_text())
    assert set(res["summary"]) == {"published (frozen)", "joint from published", "spiral (frozen)",
                                   "joint from spiral"}
    frozen = res["runs"]["published (frozen)"]
    assert frozen["0"]["lsr"] == frozen["1"]["lsr"]  # the frozen mask did not move
    assert res["scenes"] == 2 + len(list(scenes.glob("*.png")))
    assert (tmp_path / "study.md").is_file() and (tmp_path / "psnr_vs_lsr.png").is_file()
