"""The README's and docs' quoted figures agree with the results files they come from (benchmarks/doc_figures.py)."""
from __future__ import annotations

import json

from benchmarks.doc_figures import QUOTES, Quote, check, pct, sci


def test_every_quoted_figure_agrees_with_its_results_file():
    assert check() == []
    assert len(QUOTES) >= 13 and {q.page for q in QUOTES} >= {"README.md", "docs/codesign.md", "docs/models.md"}


def test_a_figure_that_moved_in_its_results_file_fails_the_check(tmp_path):
    source = tmp_path / "result.json"
    quote = Quote("README.md", "**LSR {}**", str(source), lambda d: (sci(d["lsr_published"]),))
    source.write_text(json.dumps({"lsr_baseline": 9.1234e-4}))  # an old key name, read under today's
    assert check([quote]) == []
    source.write_text(json.dumps({"lsr_published": 9.13e-4}))
    assert check([quote]) == [f"README.md: does not say '**LSR 9.13e-4**' (from {source})"]
    source.write_text(json.dumps({"lsr": 1.0}))
    assert check([quote]) == [f"README.md: cannot read the figures of '**LSR {{}}**' from {source}: "
                              "KeyError('lsr_published')"]


def test_formats():
    assert (sci(9.1234e-4), sci(1.0701e-3, 4), sci(0.0284, 3), pct(0.204)) == ("9.12e-4", "1.070e-3", "2.84e-2",
                                                                                 "20.4 %")
