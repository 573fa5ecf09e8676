"""Shared helpers: machine description, subprocess isolation for peak memory, atomic result writing."""
from __future__ import annotations

import datetime
import json
import os
import platform
import resource
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import torch

RESULTS = Path(__file__).resolve().parent / "results"


def machine() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return {
        "cpu": cpu, "cores": os.cpu_count(), "threads": torch.get_num_threads(), "torch": torch.__version__,
        "python": platform.python_version(), "date": datetime.date.today().isoformat(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }


def peak_rss_mb() -> float:
    """Peak resident set size of this process [MiB] (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run_isolated(module: str, args: list[str]) -> dict:
    """Run ``python -m module args`` in a fresh process (clean peak-memory reading); it prints one JSON line."""
    out = subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parent.parent)
    return json.loads(out.stdout.strip().splitlines()[-1])


def write_result(name: str, data: dict) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(tmp, path)
    return path



# ---- the suite interface (python -m benchmarks) ------------------------------------------------------------
# Each suite module (benchmarks/bench_*.py) defines ``run(scale: str, out: Path) -> Report``: it measures at
# scale "quick" (the whole suite < 10 min on 2 CPU cores) or "full", prints its tables, writes JSON and PNGs
# into ``out`` (benchmarks/results/<scale>/) and returns what docs/benchmarks.md shows.
SCALES = ("quick", "full")


@dataclass
class Report:
    """What one benchmark contributes to docs/benchmarks.md: a section title, markdown tables, figures, notes."""

    name: str
    title: str
    tables: list[str] = field(default_factory=list)  # markdown, each printed and written as-is
    figures: list[Path] = field(default_factory=list)  # PNGs under ``out``
    notes: list[str] = field(default_factory=list)  # one paragraph each (how measured, what is the default)


def markdown_table(header: list[str], rows: list[list], fmt: dict | None = None) -> str:
    """A markdown table; floats are formatted with ``fmt[column]`` (default 4 significant digits)."""
    fmt = fmt or {}

    def cell(col: str, v) -> str:
        if isinstance(v, float):
            return format(v, fmt.get(col, ".4g"))
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(h, v) for h, v in zip(header, r)) + " |" for r in rows]
    return "\n".join(lines)


def time_error_plot(path: Path, series: dict[str, list[tuple[float, float, str]]], xlabel: str, ylabel: str,
                    title: str, logy: bool = True, hline: tuple[float, str] | None = None) -> Path:
    """Run time (x) against error (y): one marker line per series of (seconds, error, point label) tuples."""
    from codesign.io.files import save_figure
    from codesign.io.plots import plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for i, (label, pts) in enumerate(series.items()):
        pts = [p for p in pts if p[1] is not None]
        if not pts:
            continue
        xs, ys = [p[0] for p in pts], [max(p[1], 1e-17) if logy else p[1] for p in pts]
        ax.plot(xs, ys, "o-", color=f"C{i % 10}", label=label, ms=4)
        for x, y, name in zip(xs, ys, [p[2] for p in pts]):
            if name:
                ax.annotate(name, (x, y), fontsize=6, xytext=(2, 2), textcoords="offset points")
    if hline is not None:
        ax.axhline(hline[0], color="0.5", ls=":", label=hline[1])
    ax.set(xscale="log", yscale="log" if logy else "linear", xlabel=xlabel, ylabel=ylabel, title=title)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    return save_figure(path, fig)


def timeit(fn, repeats: int, warmup: int = 1, sync=None) -> float:
    """Median seconds of ``repeats`` calls after ``warmup`` calls (``sync()`` before each clock read on GPU)."""
    import statistics
    import time

    for _ in range(warmup):
        fn()
    times = []
    for _ in range(max(repeats, 1)):
        if sync:
            sync()
        t0 = time.perf_counter()
        fn()
        if sync:
            sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def cuda_sync(dev):
    """``timeit``'s sync for a device: torch.cuda.synchronize on a GPU, None on the CPU."""
    return torch.cuda.synchronize if dev.type == "cuda" else None


def peak_cuda_mib(dev, reset: bool = False) -> float | None:
    """Peak allocated CUDA memory [MiB] since the last reset (``reset=True`` resets it first); None on the CPU."""
    if dev.type != "cuda":
        return None
    if reset:
        torch.cuda.reset_peak_memory_stats()
    return torch.cuda.max_memory_allocated() / 2**20


def write_json(path: Path, data: dict) -> Path:
    """Atomic JSON write (temp file, then rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(tmp, path)
    return path


def fit_exponent(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope of log y against log x: cost ~ x^k."""
    import math

    lx, ly = [math.log(x) for x in xs], [math.log(y) for y in ys]
    mx, my = sum(lx) / len(lx), sum(ly) / len(ly)
    return sum((a - mx) * (b - my) for a, b in zip(lx, ly)) / sum((a - mx) ** 2 for a in lx)
