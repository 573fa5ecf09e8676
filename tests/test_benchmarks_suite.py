"""The benchmark suite's plumbing (no timing is asserted anywhere): argument checks, fits, tables, docs rendering."""
from __future__ import annotations

import math
from pathlib import Path

import pytest

from benchmarks.__main__ import BENCHMARKS, docs_path, parse_args, render_docs
from benchmarks.common import Report, fit_exponent, markdown_table


def test_unknown_benchmark_name_is_refused_with_the_allowed_names():
    with pytest.raises(SystemExit, match=r"--only 'psf,bogus': unknown bogus; allowed: psf, mask, sensor, "
                                         r"restoration, scaling, accuracy \(comma-separated\)"):
        parse_args(["--only", "psf,bogus"])
    with pytest.raises(SystemExit, match="unknown empty list"):
        parse_args(["--only", ","])


def test_scale_and_threads_are_checked(capsys):
    with pytest.raises(SystemExit):
        parse_args(["--scale", "huge"])
    assert "invalid choice: 'huge' (choose from 'quick', 'full')" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parse_args(["--threads", "0"])
    assert "--threads 0: must be between 1 and" in capsys.readouterr().err
    a = parse_args(["--only", "mask, psf"])
    assert a.names == ["mask", "psf"] and a.scale == "quick"
    assert parse_args([]).names == list(BENCHMARKS)


def test_fit_exponent_recovers_a_power_law():
    xs = [2.0, 3.0, 5.0, 8.0]
    assert fit_exponent(xs, [7.0 * x**1.5 for x in xs]) == pytest.approx(1.5, abs=1e-12)
    assert fit_exponent(xs, [x ** -2.0 for x in xs]) == pytest.approx(-2.0, abs=1e-12)


def test_markdown_table_formats_floats_per_column():
    t = markdown_table(["name", "ms", "err"], [["a", 1.23456, 1e-5], ["b", 10.0, math.nan]], {"ms": ".1f"})
    assert t.splitlines() == ["| name | ms | err |", "|---|---|---|", "| a | 1.2 | 1e-05 |", "| b | 10.0 | nan |"]


def test_docs_rendering_holds_machine_tables_figures_and_paths(tmp_path):
    info = {"cpu": "CPU X", "cores": 2, "threads": 2, "cuda": None, "torch": "2.x", "python": "3.11", "date": "d"}
    out = docs_path("quick").parent.parent / "benchmarks" / "results" / "quick"
    rep = Report("psf", "PSF title", ["| a |\n|---|\n| 1 |"], [out / "psf_lsr_error.png"], ["a note"])
    text = render_docs([rep], info, "quick", {"psf": 60.0}, out)
    assert "CPU X, 2 cores, 2 torch threads, no GPU; torch 2.x" in text
    assert "suite wall time 1.0 min (psf 60 s)" in text
    assert "## PSF title\n\na note\n\n| a |" in text
    assert "![psf_lsr_error](../benchmarks/results/quick/psf_lsr_error.png)" in text
    assert docs_path("quick").name == "benchmarks.md" and docs_path("full").name == "benchmarks_full.md"
    assert isinstance(docs_path("full"), Path)
