"""One name per figure: today's metrics keys, and the exact mapping from the names older files carry."""
from __future__ import annotations

import json

import pytest

from codesign.data.params import alpha_tag, laser_preset_name
from codesign.io.metric_names import main, new_name, read_metrics, upgrade


@pytest.mark.parametrize("old, new", [
    ("psnr_affine", "psnr_matched"),
    ("ssim_affine_sgan_laser_1e6", "ssim_matched_sgan_laser_1e6"),
    ("lsr_baseline", "lsr_published"),
    ("psnr_affine_baseline_laser_0", "psnr_matched_published_laser_0"),
    ("evaluation_per_scene_psnr_affine_baseline", "evaluation_per_scene_psnr_matched_published"),
    ("lsr_vs_baseline", "lsr_vs_published"),
    ("net_psnr_affine_1e6", "net_psnr_matched_1e6"),
    ("saturated_fraction_alpha_l_1e+06", "saturated_fraction_alpha_l_1e6"),
    ("laser_peak_alpha_l_2.5e+05", "laser_peak_alpha_l_2.5e5"),
    # unchanged: today's names, and keys that start with the word (the memory and calibration baselines)
    ("psnr_matched_published", "psnr_matched_published"),
    ("baseline_rss_mb", "baseline_rss_mb"),
    ("baseline_calibration", "baseline_calibration"),
    ("saturated_fraction_alpha_l_0", "saturated_fraction_alpha_l_0"),
])
def test_new_name(old, new):
    assert new_name(old) == new


def test_upgrade_renames_at_every_depth_and_reports_what_it_renamed():
    old = {"lsr_baseline": 1e-3, "evaluation_baseline": {"laser_1e6": {"sgan": {"psnr_affine": 20.5, "psnr": 18.0}}},
           "runs": [{"ssim_affine": 0.5}], "network": "sgan_b_gated"}
    new, renamed = upgrade(old)
    assert new == {"lsr_published": 1e-3, "evaluation_published": {"laser_1e6": {"sgan": {"psnr_matched": 20.5,
                                                                                           "psnr": 18.0}}},
                   "runs": [{"ssim_matched": 0.5}], "network": "sgan_b_gated"}
    assert renamed == {"lsr_baseline": "lsr_published", "evaluation_baseline": "evaluation_published",
                       "psnr_affine": "psnr_matched", "ssim_affine": "ssim_matched"}
    assert upgrade(new) == (new, {})


def test_an_old_and_a_new_key_for_one_figure_is_an_error():
    with pytest.raises(ValueError, match="key 'lsr_baseline' would become 'lsr_published', which the same object "
                                         "already holds"):
        upgrade({"lsr_baseline": 1.0, "lsr_published": 2.0})


def test_the_command_checks_and_rewrites_files(tmp_path, capsys):
    old, new = tmp_path / "old.json", tmp_path / "new.json"
    old.write_text(json.dumps({"psnr_affine": 1.0, "lsr_baseline": 2.0}))
    new.write_text(json.dumps({"psnr_matched": 1.0}))
    assert main(["--check", str(old), str(new)]) == 1
    assert capsys.readouterr().out == f"{old}: lsr_baseline -> lsr_published, psnr_affine -> psnr_matched\n"
    assert json.loads(old.read_text()) == {"psnr_affine": 1.0, "lsr_baseline": 2.0}  # --check writes nothing
    assert main([str(old)]) == 0 and json.loads(old.read_text()) == {"lsr_published": 2.0, "psnr_matched": 1.0}
    assert main(["--check", str(old), str(new)]) == 0
    assert read_metrics(old) == {"lsr_published": 2.0, "psnr_matched": 1.0}


@pytest.mark.parametrize("v, tag", [(0, "0"), (1, "1"), (1.5, "1.5"), (10, "1e1"), (300, "3e2"), (1e3, "1e3"),
                                    (2.5e5, "2.5e5"), (1e6, "1e6"), (2e6, "2e6")])
def test_alpha_l_is_written_one_way(v, tag):
    assert alpha_tag(v) == tag
    assert laser_preset_name(v) == f"laser_{tag}"
