"""``python -m codesign.io.metric_names FILE...``: every file is read and checked before any is rewritten (a missing
file, a folder, a file that is not JSON or one whose old and new names clash stop it with one line naming the file,
nothing rewritten), each rewrite is atomic, and NaN / Infinity stay what they were (json writes them back)."""
from __future__ import annotations

import json
import math
import re

import pytest

from codesign.io.metric_names import main

PROG = "python -m codesign.io.metric_names: "


def _old(tmp_path, name="a.json", extra=None):
    path = tmp_path / name
    path.write_text(json.dumps({"psnr_affine": 1.0, **(extra or {})}))
    return path


@pytest.mark.parametrize("bad,why", [
    ("missing", "no such file"),
    ("folder", "is a folder, not a JSON file"),
    ("text", r"is not JSON \(Expecting value: line 1 column 1 \(char 0\)\)"),
    ("clash", r"cannot be renamed: key 'psnr_affine' would become 'psnr_matched', which the same object already "
              "holds"),
], ids=["missing", "folder", "text", "clash"])
def test_a_bad_file_stops_the_command_before_any_file_is_rewritten(tmp_path, capsys, bad, why):
    good = _old(tmp_path)
    before = good.read_text()
    path = tmp_path / "b.json"
    if bad == "folder":
        path.mkdir()
    elif bad == "text":
        path.write_text("not json")
    elif bad == "clash":
        path.write_text(json.dumps({"psnr_affine": 1.0, "psnr_matched": 2.0}))
    assert main([str(good), str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert re.fullmatch(re.escape(f"{PROG}{path}: ") + why + re.escape("; nothing was rewritten (every file is "
                                                                       "checked before any is)"), err[0]), err[0]
    assert good.read_text() == before  # the first file was rewritten before the second failed


def test_nan_and_infinity_are_kept(tmp_path):
    path = tmp_path / "m.json"
    path.write_text('{"psnr_affine": NaN, "lsr_baseline": Infinity, "x": [-Infinity, 1]}')
    assert main([str(path)]) == 0
    data = json.loads(path.read_text())  # they were written as null
    assert math.isnan(data["psnr_matched"]) and data["lsr_published"] == math.inf and data["x"][0] == -math.inf
