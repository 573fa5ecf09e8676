"""Mask records (mask.init=FILE) read whole: every key used or refused by the rules of the config key it stands for,
a record made for other optics refused, the file's size and nesting bounded before it is read, a key given twice
refused, all before any work and with the file named in the message; a record's levels kept (psf, export)."""
from __future__ import annotations

import gzip
import json
import logging

import pytest
import torch

from codesign.experiments.specs import plate_settings
from codesign.optics import OpticsSpec
from codesign.optics.grid import PupilGrid
from codesign.optics.masks import PUBLISHED_R, PUBLISHED_THETA, build_mask, quantize
from codesign.optics.masks.records import RECORD_PATH, optics_record, record_keys
from tests.inputs._run import compose_cfg, config_error

OPTICS = optics_record(OpticsSpec())  # the configured optics of every experiment (debug=smoke keeps them)
HALFRING = {"kind": "halfring", "r": list(PUBLISHED_R), "theta": list(PUBLISHED_THETA), "convention": "atan2",
            "harmonic_sign": "printed", "m_range": [1, 17], "r_bounds": [0.5, 100.0], "levels": 8, "optics": OPTICS,
            "lsr": 0.0064, "feasible": True}
SPLINE = {"kind": "spline", "control_pitch_m": 2e-5, "control_half": 52, "controls": [0.0] * 105**2, "levels": None,
          "optics": OPTICS}
ZERNIKE = {"kind": "zernike", "coeffs": [0.5] * 10, "n_terms": 36, "max_coeff_rad": 50.0, "optics": OPTICS}
PIXEL = {"kind": "pixel", "grid_n": 402, "pitch_m": 9.974e-6, "values": [0.0] * 10, "optics": OPTICS}
WHOLE = f"must be null or {RECORD_PATH}"  # the start of a message about the file as a whole
MAX_VALUE = "must be a finite number >= -1e+06 and <= 1e+06"

# (experiment, record, the message after "mask.init FILE: ") for a value of the record
VALUES = [
    ("psf", {**HALFRING, "levels": 1}, "levels = 1: must be an integer >= 2 and <= 65536"),
    ("psf", {**HALFRING, "levels": "8"}, "levels = '8': must be an integer >= 2 and <= 65536"),
    ("export", {**HALFRING, "levels": True}, "levels = True: must be an integer >= 2 and <= 65536"),
    ("psf", {**HALFRING, "optics": {**OPTICS, "wavelength_m": 1.064e-6}},
     "optics.wavelength_m = 1.064e-06: the design was made for these optics, not the configured optics.wavelength_m "
     "= 6.33e-07: set optics.wavelength_m=1.064e-06 to use it as designed, or design one for these optics"),
    ("export", {**HALFRING, "optics": {**OPTICS, "aperture_diameter_m": 5e-3}},
     "optics.aperture_diameter_m = 0.005: the design was made for these optics, not the configured "
     "optics.aperture_diameter_m = 0.00383: set optics.aperture_diameter_m=0.005 to use it as designed, or design "
     "one for these optics"),
    ("psf", {**HALFRING, "optics": {**OPTICS, "wavelength_m": -1}},
     "optics.wavelength_m = -1: must be a finite number >= 1e-08 and <= 0.0001"),
    ("psf", {**HALFRING, "optics": {**OPTICS, "colour": "red"}},
     "optics.colour = 'red': unknown key; allowed: " + ", ".join(sorted(OPTICS))),
    ("psf", {**HALFRING, "optics": "633 nm"},
     "optics = '633 nm': must be the optics the design was made for: a mapping of optics keys (wavelength_m, "
     "focal_length_m, ...)"),
    ("psf", {**HALFRING, "m_range": [5, 2]}, "m_range[1] = 2: must be an integer >= 5 and <= 99"),
    ("psf", {**HALFRING, "convention": "atan3"}, "convention = 'atan3': must be one of atan, atan2"),
    ("psf", {**HALFRING, "r_bounds": 7}, "r_bounds = 7: must be [lo, hi] with 0 < lo < hi"),
    ("psf", {**HALFRING, "theta": [1e30, 1, 1, 1, 1]},
     "theta[0] = 1e+30: must be a finite number >= -10000 and <= 10000"),
    ("psf", {**HALFRING, "lsr": "low"}, "lsr = 'low': must be a finite number"),
    ("psf", {**HALFRING, "feasible": 1}, "feasible = 1: must be true, false or null"),
    ("tolerance", {**SPLINE, "controls": [0.0] * 10},  # was a RuntimeError (reshape) after the run folder was made
     "controls = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]: must hold (2 control_half + 1)^2 = 11025 "
     "control values (control_half = 52), it holds 10"),
    ("tolerance", {**SPLINE, "controls": [1e30] * 105**2}, f"controls[0] = 1e+30: {MAX_VALUE}"),  # was analysed
    ("tolerance", {**SPLINE, "control_half": 2.5}, "control_half = 2.5: must be an integer >= 1 and <= 100000"),
    ("export", {**ZERNIKE}, "coeffs = [0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5]: must hold n_terms = 36 "
     "coefficients, it holds 10"),
    ("export", {**ZERNIKE, "n_terms": 10, "coeffs": [0.5] * 9 + [-2e6]}, f"coeffs[9] = -2000000.0: {MAX_VALUE}"),
    ("export", {**PIXEL}, "values = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]: must hold one phase per "
     "sample of its grid inside the aperture (125081 for grid_n = 402, pitch_m = 9.974e-06), it holds 10"),
    ("export", {**PIXEL, "grid_n": 100}, "grid_n = 100: its grid (100 x 9.97e-06 m) cannot hold the aperture "
     "(W_a = 0.00383 m): must be >= 402"),
]


def _refusal(monkeypatch, capsys, tmp_path, experiment: str, content: str) -> tuple[str, str]:
    """The error line of ``+experiment=...`` with mask.init a file holding ``content``, and the file's path."""
    path = tmp_path / "best_mask.json"
    path.write_text(content)
    line = config_error(monkeypatch, capsys, tmp_path / "run", f"+experiment={experiment}", "debug=smoke",
                        f"mask.init={path}")
    assert not (tmp_path / "run").exists()  # refused before any run folder is kept
    return line, str(path)


@pytest.mark.parametrize("experiment,record,message", VALUES, ids=[m.split(":")[0] for _, _, m in VALUES])
def test_a_bad_value_in_a_record_is_refused_naming_the_file_and_its_key(experiment, record, message, monkeypatch,
                                                                       capsys, tmp_path):
    line, path = _refusal(monkeypatch, capsys, tmp_path, experiment, json.dumps(record))
    assert line == f"codesign: configuration error: mask.init {path}: {message}"


def test_a_key_given_twice_is_refused_with_both_values(monkeypatch, capsys, tmp_path):
    text = json.dumps(HALFRING)[:-1] + ', "levels": 16}'  # json.loads would keep 16 without a word
    line, path = _refusal(monkeypatch, capsys, tmp_path, "psf", text)
    assert line == (f"codesign: configuration error: mask.init {path}: levels = 8, then 16: given more than once: "
                    f"a record's keys must be unique (which value is meant cannot be told)")


def test_a_spec_key_that_no_record_holds_is_refused(monkeypatch, capsys, tmp_path):
    # preset (and strategy, rings, ...) build a mask from a config; a record's own r and theta would win unseen
    line, path = _refusal(monkeypatch, capsys, tmp_path, "psf", json.dumps({**HALFRING, "preset": "published"}))
    assert line == (f"codesign: configuration error: mask.init = '{path}': {WHOLE}; its key(s) preset are not keys "
                    f"of a halfring record (allowed: {', '.join(sorted(record_keys('halfring')))})")


@pytest.mark.parametrize("make,message", [
    (lambda p: p.open("wb").truncate(33 * 2**20),  # sparse: written at once; never read
     "it holds 33.0 MiB, more than any mask record (at most 32 MiB: a pixel record of ~2.8 million phases): "
     "not read"),
    (lambda p: p.write_text('{"kind": "spline", "levels": ' + "[" * 100000 + "]" * 100000 + "}"),
     "it nests lists or objects deeper than Python reads (a mask record nests two levels)"),
    (lambda p: p.mkdir(), "it is a directory"),
    (lambda p: p.write_bytes(gzip.compress(b" " * (33 * 2**20), 1)),  # 33 kB that unpack to 33 MiB
     "it unpacks to more than any mask record (at most 32 MiB: a pixel record of ~2.8 million phases): not read"),
    (lambda p: p.write_bytes(gzip.compress(json.dumps(HALFRING).encode())[:-12]),
     "cannot be unpacked as gzip (Compressed file ended before the end-of-stream marker was reached)"),
], ids=["33MiB", "nested", "directory", "gzip-33MiB", "gzip-cut-short"])
def test_a_file_no_record_can_be_is_refused_before_it_is_read(make, message, monkeypatch, capsys, tmp_path):
    path = tmp_path / "best_mask.json"
    make(path)
    line = config_error(monkeypatch, capsys, tmp_path / "run", "+experiment=tolerance", "debug=smoke",
                        f"mask.init={path}")
    assert line == f"codesign: configuration error: mask.init = '{path}': {WHOLE}; {message}"
    assert not (tmp_path / "run").exists()


@pytest.fixture(scope="module")
def grid():
    spec = OpticsSpec(pupil_pitch_m=4e-5, focal_n=64)
    return PupilGrid.from_spec(spec, dtype=torch.float64)


def test_a_records_levels_are_kept(grid, tmp_path):
    # an 8-level design reloaded by mask.init stays one (it became continuous: LSR 0.00858 instead of 0.00644)
    (tmp_path / "m.json").write_text(json.dumps(HALFRING))
    mask = build_mask({"kind": "halfring", "init": str(tmp_path / "m.json")}, grid, 3.83e-3)
    continuous = build_mask({"kind": "halfring"}, grid, 3.83e-3).phase()
    assert mask.levels == 8
    assert torch.equal(mask.phase(), grid.scatter(quantize(continuous.reshape(-1)[grid.support], 8)))


def test_a_gzip_compressed_record_is_read_as_the_same_design(grid, tmp_path):
    # benchmarks/results keeps its spline and pixel records as best_mask.json.gz (2.3x smaller)
    (tmp_path / "m.json").write_text(json.dumps(HALFRING))
    (tmp_path / "m.json.gz").write_bytes(gzip.compress(json.dumps(HALFRING).encode()))
    plain, packed = (build_mask({"kind": "halfring", "init": str(tmp_path / name)}, grid, 3.83e-3)
                     for name in ("m.json", "m.json.gz"))
    assert packed.levels == plain.levels == 8 and torch.equal(packed.phase(), plain.phase())


def test_a_configured_levels_quantizes_a_record_anew_and_says_so(grid, tmp_path, caplog):
    path = tmp_path / "m.json"
    path.write_text(json.dumps(HALFRING))
    with caplog.at_level(logging.WARNING, logger="codesign"):
        mask = build_mask({"kind": "halfring", "init": str(path), "levels": 16}, grid, 3.83e-3)
    assert mask.levels == 16
    assert f"mask.init {path}: levels = 8 (the design's); mask.levels = 16 is used instead: the design is " \
           f"quantized to 16 levels" in caplog.messages


def test_export_makes_a_plate_of_the_designs_levels(tmp_path):
    # export.levels = null wrote a continuous plate for an 8-level design
    path = tmp_path / "m.json"
    path.write_text(json.dumps(HALFRING))
    _, ex, _, mask_cfg, _ = plate_settings(compose_cfg("+experiment=export", f"mask.init={path}"))
    assert ex.levels == 8
    _, ex, _, _, _ = plate_settings(compose_cfg("+experiment=export", f"mask.init={path}", "export.levels=4"))
    assert ex.levels == 4  # the typed export.levels wins
