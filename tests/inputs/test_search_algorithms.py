"""search.algorithm against the mask family it searches: an nlopt algorithm that cannot run a family's parameter
vector (AGS above 10 dimensions, the original DIRECT from 34, ISRES's population, SLSQP's dense matrix) is refused
before the search, naming the key, the family and the algorithms that can run it; it used to crash the process
without a word (GN_ISRES on a spline mask: exit 139) or end in a traceback in the search (GN_AGS, LD_SLSQP)."""
from __future__ import annotations

import re

import pytest

from codesign.design.optimize import ALGORITHMS, LOCAL, SIZE_LIMITS
from codesign.design.search_spec import SearchSpec
from codesign.errors import ConfigError
from tests.inputs._run import config_error

ERR = "codesign: configuration error: "


@pytest.mark.parametrize("algorithm,n,family", [("GN_ISRES", 11025, "spline"), ("GN_AGS", 11025, "spline"),
                                                ("LD_SLSQP", 11025, "spline"), ("GN_AGS", 36, "zernike"),
                                                ("GN_ORIG_DIRECT", 36, "zernike"), ("GN_ORIG_DIRECT_L", 125081, "pixel")])
def test_an_algorithm_that_cannot_run_a_family_is_refused_naming_what_can(algorithm, n, family):
    limit = SIZE_LIMITS[algorithm][0]
    fits = [a for a in ALGORITHMS if SIZE_LIMITS.get(a, (n,))[0] >= n]
    with pytest.raises(ConfigError, match="^" + re.escape(f"search.algorithm = '{algorithm}': cannot search a "
                                                          f"{family} mask of {n} parameters (at most {limit}: ") +
                       ".*" + re.escape(f"); allowed for this mask: {', '.join(fits)}") + "$"):
        SearchSpec(algorithm=algorithm, local_algorithm="LD_MMA").check_size(n, family)


def test_the_algorithms_that_fit_run_and_a_global_search_s_polish_is_checked_too():
    for algorithm in ALGORITHMS:  # the half rings' 10 parameters: every algorithm runs them
        SearchSpec(algorithm=algorithm).check_size(10, "halfring")
    SearchSpec(algorithm="auto").check_size(125081, "pixel")  # auto: AL_LBFGS above 64 parameters
    with pytest.raises(ConfigError, match=r"^search.local_algorithm = 'LD_SLSQP': cannot search a spline mask of "
                                          r"900 parameters .*; allowed for this mask: " + ", ".join(
                                              a for a in LOCAL if a != "LD_SLSQP") + "$"):
        SearchSpec(algorithm="GN_ISRES", local_algorithm="LD_SLSQP").check_size(900, "spline")
    SearchSpec(algorithm="GN_ISRES", local_algorithm="LD_SLSQP", polish_max_evals=0).check_size(900, "spline")


def test_mask_search_refuses_the_pair_before_any_work(monkeypatch, capsys, tmp_path):
    line = config_error(monkeypatch, capsys, tmp_path / "run", "+experiment=mask_search", "debug=smoke",
                        "mask=zernike", "search.algorithm=GN_AGS")
    assert line.startswith(f"{ERR}search.algorithm = 'GN_AGS': cannot search a zernike mask of 36 parameters (at "
                           f"most 10: nlopt's AGS takes at most 10 dimensions")
    assert not (tmp_path / "run").exists()


@pytest.mark.slow  # 5 s: the command line that crashed (exit 139, nothing printed); twin: the in-process test above
def test_cli_mask_search_of_a_spline_mask_with_isres(tmp_path):
    from tests.cli import run_codesign

    run_dir = tmp_path / "run"
    proc = run_codesign("+experiment=mask_search", "debug=smoke", "threads=1", "mask=spline",
                        "search.algorithm=GN_ISRES", f"hydra.run.dir={run_dir}")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1].startswith(
        f"{ERR}search.algorithm = 'GN_ISRES': cannot search a spline mask of 11025 parameters (at most 1000: ")
    assert "Traceback" not in proc.stderr and not run_dir.exists()
