"""Config values that passed silently or were named wrongly (issue 59 item 3, group A): each is now refused before
any work (exit 2) with one line naming the key, the value and what is allowed, or warned about in one line naming
both keys; the entry point expands ~ in the run folders and adds a quoting hint to Hydra's override parse error."""
from __future__ import annotations

import json
import logging
import sys

import pytest

import codesign.__main__ as entry
from codesign.config.argv import expand_run_dirs
from codesign.errors import ConfigError
from codesign.sensor.spec import SensorSpec
from codesign.experiments.specs import eval_settings
from codesign.train import memory as train_memory
from tests.inputs._run import compose_cfg, config_error

ERR = "codesign: configuration error: "
BIT_DEPTH = "must be an integer >= 8 and <= 24 (image sensors digitize with 8 to 16 bits, scientific cameras up to 24)"
INDEX = "a mask material needs 1 < n <= 5 (no optical material has more: germanium, ~4 in the infrared, is the highest)"
RECORD = ("must be null or the path of a mask record (best_mask.json of +experiment=mask_search, learned_mask.json of "
          "joint, mask.json of psf)")
SPECTRUM = ("computes the mask's PSF at optics.wavelength_m (and its laser lines) and images no scene, so it never "
            "reads the scene's spectrum: leave it null (the experiments that image scenes through the camera read it)")

ROWS = [
    # 1: a 1-bit sensor read every pixel as 1 DN and reported 0 % saturated
    ("simulate", "sensor.bit_depth=1", f"sensor.bit_depth = 1: {BIT_DEPTH}"),
    ("simulate", "sensor.bit_depth=32", f"sensor.bit_depth = 32: {BIT_DEPTH}"),
    # 2: 1e12 steps was accepted while 2.5 was refused
    ("baseline", "trainer.steps=1e12", "trainer.steps = 1000000000000.0: must be an integer >= 1 and <= 1e+07"),
    # 3: a strength listed twice was evaluated (simulated) twice
    ("baseline", "evaluate.laser_strengths=[1e6,1e6]",
     "evaluate.laser_strengths = [1000000.0, 1000000.0]: lists 1e+06 twice: give each value once"),
    ("simulate", "simulate.laser_strengths=[0,1e3,0]",
     "simulate.laser_strengths = [0.0, 1000.0, 0.0]: lists 0 twice: give each value once"),
    # 6: keys the run never reads
    ("psf", "optics.psf_energy=0.5", "optics.psf_energy = 0.5: describes optics.psf_file, which is null: give the "
     "measured PSF with optics.psf_file=PATH, or leave optics.psf_energy at 1 (the default)"),
    ("psf", "optics.scene_spectrum=[[5e-7,1]]", f"optics.scene_spectrum = [[5e-07, 1]]: +experiment=psf {SPECTRUM}"),
    ("tolerance", "optics.scene_spectrum=[[5e-7,1]]",
     f"optics.scene_spectrum = [[5e-07, 1]]: +experiment=tolerance {SPECTRUM}"),
    # 7: a refractive index of 1e6 (a 2 pi step a millionth of a wavelength deep)
    ("psf", "material=custom material.coefficients=[1e6]",
     f"material.coefficients = [1000000.0]: give n = 1e+06 at every wavelength: {INDEX}"),
    ("export", "material=custom material.formula=cauchy material.coefficients=[7.0]",
     f"material.coefficients = [7.0]: give n = 7 at 0.633 um: {INDEX}"),
    # 9: a detuning sigma whose samples left the optics' range was named as a sample's optics.wavelength_m = -5.5e-07
    ("tolerance", "tolerance.wavelength_m=1e-6", "tolerance.wavelength_m = 1e-06: its samples reach "
     "optics.wavelength_m +- 6 sigma = 6.33e-07 +- 6e-06 m, beyond the 3.76e-07..1e-04 m the optics window carries (a "
     "shorter wavelength aliases or is undersampled on it): must be >= 0 and <= 4.28e-08 m"),
    # 9: 0 samples per source ran, wrote samples.csv, then failed on a zero-size array
    ("tolerance", "tolerance.samples_per_source=0",
     "tolerance.samples_per_source = 0: must be an integer >= 1 and <= 1e+06"),
    # 10: an empty path was refused as "a directory"
    ("psf", "mask.init=''", f"mask.init = '': {RECORD}; an empty path names no file (null for none)"),
]


@pytest.mark.parametrize("experiment,overrides,message", ROWS, ids=[r[1] for r in ROWS])
def test_silent_value_is_refused_before_any_work(experiment, overrides, message, monkeypatch, capsys, tmp_path):
    line = config_error(monkeypatch, capsys, tmp_path / "run", f"+experiment={experiment}", "debug=smoke",
                        *overrides.split())
    assert line == ERR + message
    assert not (tmp_path / "run").exists()


def test_a_bit_depth_at_or_below_the_black_level_is_refused():
    # every pixel would read full scale: 255 DN is below 1.0 DN/e- x 390 e- of read-noise offset
    with pytest.raises(ConfigError, match=r"^sensor\.bit_depth = 8: its full scale 2\^8 - 1 = 255 DN is not above the "
                                          r"black level 390 DN .*every pixel would read full scale; need bit_depth >= "
                                          r"9$"):
        SensorSpec(bit_depth=8, gain_dn_per_e=1.0)
    assert SensorSpec(bit_depth=8).saturation_dn == 255.0  # Table 1's gain: 144 DN of black level fits


def test_zernike_coefficients_beyond_the_records_box_are_refused(tmp_path, monkeypatch, capsys):  # 5
    path = tmp_path / "best_mask.json"
    path.write_text(json.dumps({"kind": "zernike", "n_terms": 3, "max_coeff_rad": 50.0, "coeffs": [0.0, 1e5, 0.0]}))
    line = config_error(monkeypatch, capsys, tmp_path / "run", "+experiment=psf", "debug=smoke", "mask=zernike",
                        f"mask.init={path}")
    assert line == (f"{ERR}mask.init {path}: coeffs[1] = 100000.0: outside the coefficients' box (its "
                    f"max_coeff_rad): must be >= -50 and <= 50 rad")


def test_heldout_scores_beside_a_folder_of_scenes_are_warned_about(tmp_path, caplog):  # 4
    caplog.set_level(logging.WARNING)
    folder = ["data.scenes=folder", f"data.folder={tmp_path}"]
    eval_settings(compose_cfg("+experiment=evaluate", *folder))
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings == [f"evaluate.scenes = heldout: the scores are on the photographs shipped for evaluation "
                        f"(codesign/data/heldout/), not on data.folder = {tmp_path} (data.scenes = folder); give "
                        f"evaluate.scenes=data to score that folder's evaluate.split"]
    caplog.clear()
    eval_settings(compose_cfg("+experiment=evaluate", *folder, "evaluate.scenes=data"))
    eval_settings(compose_cfg("+experiment=evaluate"))  # the shipped scenes both ways: nothing to say
    assert not [r for r in caplog.records if r.levelno == logging.WARNING]


def test_optics_grids_that_cannot_fit_are_refused_before_any_allocation(tmp_path, monkeypatch, capsys):  # 11
    monkeypatch.setattr(train_memory, "available_bytes", lambda device: (16 * 2**30, "MemAvailable in /proc/meminfo"))
    line = config_error(monkeypatch, capsys, tmp_path / "run", "+experiment=psf", "debug=smoke",
                        "optics.pupil_pitch_m=1e-7")
    assert line == (f"{ERR}optics.pupil_pitch_m = 1e-07: the optics grids need about 76.8 GiB (a 39798 x 39798 pupil "
                    "grid, the 160 x 160 focal window, complex64, 1 wavelength(s)), more than the 16.0 GiB available "
                    "(MemAvailable in /proc/meminfo): raise optics.pupil_pitch_m, or lower optics.pupil_n, "
                    "optics.focal_n or the wavelengths (optics.laser_wavelengths_m, optics.scene_spectrum)")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("typed,expanded", [
    ("hydra.run.dir=~/x", "hydra.run.dir={home}/x"),
    ('hydra.run.dir="~/x"', 'hydra.run.dir="{home}/x"'),
    ("hydra.sweep.dir='~/s'", "hydra.sweep.dir='{home}/s'"),
    ("++hydra.run.dir=~", "++hydra.run.dir={home}"),
    ("mask.init=~/m.json", "mask.init=~/m.json"),  # expanded by the path key itself
    ("hydra.run.dir=a/~/x", "hydra.run.dir=a/~/x"),  # not leading: a folder named ~ asked for
])
def test_a_leading_tilde_of_a_run_folder_is_expanded(typed, expanded, tmp_path, monkeypatch):  # 8
    monkeypatch.setenv("HOME", str(tmp_path))
    assert expand_run_dirs([typed]) == [expanded.format(home=tmp_path)]


def _main(monkeypatch, *args: str) -> list[str]:
    """codesign's entry point on ``args`` up to Hydra: the arguments Hydra would read."""
    seen = []
    monkeypatch.setattr(sys, "argv", ["codesign", *args])
    monkeypatch.setattr(entry, "_hydra_main", lambda: seen.append(list(sys.argv[1:])))
    entry.main()
    return seen[0]


def test_the_entry_point_hands_hydra_the_expanded_run_folders(tmp_path, monkeypatch):  # 8
    monkeypatch.setenv("HOME", str(tmp_path))
    assert _main(monkeypatch, "+experiment=psf", "hydra.run.dir=~/x", 'hydra.sweep.dir="~/s"') == [
        "+experiment=psf", f"hydra.run.dir={tmp_path}/x", f'hydra.sweep.dir="{tmp_path}/s"']


def test_an_override_cut_at_a_space_keeps_hydras_message_and_adds_a_quoting_hint(monkeypatch, capsys):  # 12
    with pytest.raises(SystemExit) as info:
        _main(monkeypatch, "+experiment=restore", "input=/tmp/a", "b.png")  # input=/tmp/a b.png, unquoted
    assert info.value.code == 1
    err = capsys.readouterr().err.splitlines()
    assert err[:2] == ["Error parsing override 'b.png'", "missing EQUAL at '<EOF>'"]  # Hydra's own
    assert err[-1] == ("codesign: hint: 'b.png' looks like the rest of input's value, cut at a space by the shell: "
                       "quote the whole override, the value in double quotes: 'input=\"/tmp/a b.png\"'")
    with pytest.raises(SystemExit):
        _main(monkeypatch, "+experiment=psf", "mask.init=(")
    assert capsys.readouterr().err.splitlines()[-1] == (
        "codesign: hint: a value holding spaces or any of ()[]{}=,:'\"\\ must be quoted for Hydra inside the shell's "
        "quotes, e.g. 'mask.init=\"(\"'")
