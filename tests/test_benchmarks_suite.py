"""The benchmark suite's plumbing (no timing is asserted anywhere): the registry, argument checks, fits, tables,
docs rendering."""
from __future__ import annotations

import ast
import importlib
import math
from pathlib import Path

import pytest

from benchmarks.__main__ import BENCHMARKS, docs_path, parse_args, render_docs
from benchmarks.common import Report, compact_png, fit_exponent, markdown_table

BENCH_DIR = Path(__file__).resolve().parent.parent / "benchmarks"
# reserved in the registry while its module is written elsewhere: checked once it exists
PENDING = {"design"}


def _present(name: str) -> bool:
    return (BENCH_DIR / f"bench_{name}.py").is_file()


@pytest.mark.parametrize("name", BENCHMARKS)
def test_every_registered_benchmark_is_a_module_with_a_run_function(name):
    if name in PENDING and not _present(name):
        pytest.skip(f"benchmarks/bench_{name}.py is not written yet (name reserved)")
    module = importlib.import_module(f"benchmarks.bench_{name}")
    assert callable(getattr(module, "run", None)), f"benchmarks/bench_{name}.py has no run(scale, out)"


def test_benchmarks_holds_the_suite_and_its_helpers_only():
    """No one-off studies beside the suite (they leave; docs/results_log.md names the commit that has each):
    __main__, common, one bench_<name>.py per registry entry, the GPU campaign (gpu.py), which runs parts of entries
    on a GPU node as __main__ runs them all, the check of the docs' quoted figures against their results files
    (doc_figures.py), and the commands that made figures the docs still show: every restorer side by side
    (restorer_table.py) and the shipped restorer's evaluation mask by mask (pretrained_eval.py; it trains with the
    package's own command, codesign/models/pretrained/README.md)."""
    modules = {p.name for p in BENCH_DIR.glob("*.py")}
    allowed = {"__init__.py", "__main__.py", "common.py", "gpu.py", "doc_figures.py", "restorer_table.py",
               "pretrained_eval.py"} | \
        {f"bench_{n}.py" for n in BENCHMARKS}
    assert modules <= allowed, f"not part of the suite: {sorted(modules - allowed)}"
    assert not [p for p in BENCH_DIR.iterdir() if p.is_dir() and p.name not in ("results", "__pycache__")]
    assert len(set(BENCHMARKS)) == len(BENCHMARKS)


def _benchmark_imports(path: Path) -> list[tuple[str, str]]:
    """(module, name) of every import from the benchmarks package in ``path`` (name "" for a plain import)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] == "benchmarks":
            out += [(node.module, a.name) for a in node.names]
        elif isinstance(node, ast.Import):
            out += [(a.name, "") for a in node.names if a.name.split(".")[0] == "benchmarks"]
    return out


def test_benchmarks_share_helpers_through_common_only():
    """An entry imports from benchmarks.common (helpers) and benchmarks.__main__ (standalone) only, and no private
    names: nothing from another entry. The GPU campaign (gpu.py) may also use the entries' public names."""
    for path in sorted(BENCH_DIR.glob("*.py")):
        for module, name in _benchmark_imports(path):
            target = module if not name or module != "benchmarks" else f"benchmarks.{name}"
            if path.name == "gpu.py" and target.startswith("benchmarks.bench_"):
                assert not name.startswith("_"), f"gpu.py imports private {name} from {module}"
                continue
            assert target in ("benchmarks.common", "benchmarks.__main__"), \
                f"{path.name} imports {target}: shared helpers belong in benchmarks/common.py"
            assert not (name.startswith("_") and target == module), f"{path.name} imports private {name} from {module}"


def test_unknown_benchmark_name_is_refused_with_the_allowed_names():
    allowed = ", ".join(BENCHMARKS)
    with pytest.raises(SystemExit, match=rf"--only 'psf,bogus': unknown bogus; allowed: {allowed} "
                                         r"\(comma-separated\)"):
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


def test_a_plot_is_stored_with_256_colours_and_other_images_as_they_are(tmp_path):
    """compact_png keeps benchmarks/results small (issue 58): a plot's flat colours stay exact."""
    import numpy as np
    from PIL import Image

    rng = np.random.default_rng(0)
    plot = np.full((60, 80, 4), 255, np.uint8)
    plot[20:40, :, :3] = rng.integers(0, 256, (20, 80, 3))  # 1,600 colours: more than a palette holds
    plot[:10, :10, :3] = (31, 119, 180)  # a line's colour
    Image.fromarray(plot, "RGBA").save(tmp_path / "plot.png")
    with Image.open(compact_png(tmp_path / "plot.png")) as im:
        assert im.mode == "P" and len(im.getcolors()) <= 256
        out = np.asarray(im.convert("RGB"))
    assert (out[40:] == 255).all() and (out[:10, :10] == (31, 119, 180)).all()
    assert np.abs(out.astype(int) - plot[..., :3]).mean() < 10
    for name, image in (("photo.png", Image.fromarray(plot[..., 0], "L")), ("clear.png", Image.new("RGBA", (4, 4)))):
        image.save(tmp_path / name)  # a grayscale photograph, a transparent image: left alone
        before = (tmp_path / name).read_bytes()
        assert compact_png(tmp_path / name).read_bytes() == before


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


def test_peers_section_skips_a_missing_peer_with_a_line_saying_so():
    from benchmarks import bench_peers

    assert bench_peers._import_peer("no_such_peer_library") is None
    row = {"samples": 384, "grid_n": 402, "threads": 1, "dtype": "float32", "library": "codesign (czt)",
           "forward_s": 0.01, "lsr_sampled": 0.00856, "max_rel_psf_diff": 0.0, "codesign_forward_backward_s": 0.03}
    data = {"threads": {"1": {"rows": [row], "versions": {"torch": "2", "numpy": "2", "hcipy": None, "prysm": None,
                                                          "poppy": None}}}}
    rep = bench_peers.report(data)
    assert 'Not installed, skipped: hcipy, prysm, poppy (pip install -e ".[peers]")' in rep.notes[0]
    assert "| 384 | 1 | float32 | codesign (czt) | 10.0 | 1.00 |" in rep.tables[0]


def test_peers_worker_refuses_thread_pools_set_after_python_started(monkeypatch):
    """numpy's BLAS reads its thread count once, when it loads: a worker whose environment does not hold the cell's
    thread count would time peers' matrix products on every core (measure() sets it for the child process)."""
    from benchmarks import bench_peers

    for var in bench_peers.THREAD_VARS:
        monkeypatch.setenv(var, "1")
    monkeypatch.delenv("MKL_NUM_THREADS")
    with pytest.raises(SystemExit, match=r"^bench_peers worker --threads 1: the thread pools must be set before "
                                         r"Python starts \(MKL_NUM_THREADS=None\); run it through measure\(\)$"):
        bench_peers.worker(["--threads", "1", "--samples", "384"])


def test_the_restorer_table_refuses_unknown_restorers_and_renders_gains_and_step_times(tmp_path, capsys):
    from benchmarks import restorer_table as rt

    with pytest.raises(SystemExit):
        rt.main(["--out", str(tmp_path), "--restorers", "sgan_b,unet9"])
    assert f"--restorers: unknown ['unet9']; allowed: {', '.join(rt.ALLOWED)}" in capsys.readouterr().err
    assert rt.ALLOWED[-1] == "sgan_b_l1" and "sgan_b_l1" not in rt.RESTORERS  # allowed, not in the default table

    def cell(psnr, plain, ssim):
        return {"psnr_matched": psnr, "psnr": plain, "ssim": ssim}

    alpha = {a: {"sgan": cell(25.0 + i, 20.0, 0.5), "wiener": cell(24.0, 23.0, 0.6), "sensor": cell(22.0, 21.0, 0.4),
                 "gain_over_wiener": {"mean": 1.0 + i, "interval": 0.25}} for i, a in enumerate(rt.ALPHAS)}
    rows = {"sgan_b": {"steps": 10, "seconds": 30.0, "eval": {"alpha": alpha}}}
    lines = rt.table(rows, times={"sgan_b": 1.5}).splitlines()
    assert lines[2] == "| sensor |  |  | 22.00 | 22.00 | 22.00 | 22.00 | 21.00 / 0.400 | 21.00 / 0.400 |"
    assert lines[4] == ("| sgan_b | 10 | 1.50 | 25.00 (+1.00 +- 0.25) | 26.00 (+2.00 +- 0.25) | 27.00 (+3.00 +- 0.25) "
                        "| 28.00 (+4.00 +- 0.25) | 20.00 / 0.500 | 20.00 / 0.500 |")
    assert rt.table({"sgan_b": {"steps": 10, "seconds": 30.0}}).splitlines()[2] == "| sgan_b | 10 | 3.00 |"
