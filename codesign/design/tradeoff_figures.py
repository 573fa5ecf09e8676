"""Figures of the design: LSR against mtf_mean with the physical limit curve (a search's evaluations and fronts,
or several families' fronts side by side)."""
from __future__ import annotations

import numpy as np

from codesign.io.plots import plt


def limit_line(ax, limit, mtf_range: tuple[float, float], label: str = "physical limit (any phase mask)") -> None:
    """Draw the smallest LSR any phase-only mask can have against mtf_mean (design/limits.py)."""
    lo, hi = mtf_range
    xs = np.linspace(max(lo, 1e-4), min(hi, limit.uncoded_mtf_mean * 0.999), 80)
    ax.plot(xs, [limit.lsr_limit(float(x)) for x in xs], "k--", lw=1.2, label=label)


def lsr_mtf_figure(points: dict[str, list[tuple[float, float]]], limit, references: dict[str, tuple[float, float]],
                   title: str, floors: list[float] | None = None):
    """LSR (log) against mtf_mean: a marker series per entry of ``points`` (name -> [(mtf_mean, lsr)]), the limit
    curve, reference masks (name -> (mtf_mean, lsr)) as stars and the MTF floors as dotted lines."""
    fig, ax = plt.subplots(figsize=(6.8, 4.8))
    xs = [m for pts in points.values() for m, _ in pts] + [m for m, _ in references.values()]
    ys = [v for pts in points.values() for _, v in pts] + [v for _, v in references.values()]
    span = (0.5 * min(xs), 1.3 * max(xs)) if xs else (0.01, 0.1)
    limit_line(ax, limit, span)
    markers = "os^Dvp<>h"
    for i, (name, pts) in enumerate(points.items()):
        if pts:  # distinct markers too: designs of different families can land on the same point
            arr = np.array(sorted(pts))
            ax.plot(arr[:, 0], arr[:, 1], markers[i % len(markers)] + ("-" if len(arr) > 1 else ""), ms=5,
                    color=f"C{i}", mfc="none", label=name)
    for j, (name, (m, v)) in enumerate(references.items()):  # references in black / greys, apart from the series
        ax.plot([m], [v], "*", ms=13, color=str(0.45 * j), label=name)
    for f in floors or ():
        ax.axvline(f, color="0.6", ls=":", lw=0.8)
    if ys:
        ax.set_ylim(min(min(ys), limit.lsr_limit(span[0])) / 1.5, max(ys) * 1.8)
    ax.set(yscale="log", xlim=span, xlabel="mtf_mean (band mean of the radial MTF)", ylabel="LSR (peak / uncoded peak)",
           title=title)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    return fig


def evaluations_figure(sweeps, front: list[dict], base: dict, limit, p_label: str):
    """A search's evaluations (sampled LSR against mtf_mean; darker: feasible under their floor), the best point per
    floor, the published mask and the limit curve."""
    fig, ax = plt.subplots(figsize=(6.8, 4.8))
    evs = [ev for sw in sweeps for ev in sw.problem.records]
    for feasible, colour, label in ((False, "0.85", "other evaluations"), (True, "0.55", "feasible evaluations")):
        pts = np.array([(ev.mtf_mean, ev.lsr_sampled) for ev in evs if ev.feasible == feasible]).reshape(-1, 2)
        ax.scatter(pts[:, 0], pts[:, 1], s=4, c=colour, label=label)
    ok = sorted((f for f in front if f["feasible"]), key=lambda f: f["mtf_floor"] or 0)
    if ok:
        ax.plot([f["mtf_mean"] for f in ok], [f["lsr"] for f in ok], "o-", color="C0",
                label="best per floor (continuous peak)")
    ax.plot([base["mtf_mean"]], [base["lsr"]], "*", ms=14, color="C3", label="published mask")
    shown = [f["lsr"] for f in ok] + [base["lsr"]] + [ev.lsr_sampled for ev in evs if ev.feasible]
    mtfs = [ev.mtf_mean for ev in evs] + [base["mtf_mean"]]
    span = (0.5 * min(mtfs), 1.3 * max(mtfs))
    limit_line(ax, limit, span)
    for f in front:
        if f["mtf_floor"]:
            ax.axvline(f["mtf_floor"], color="C0", ls=":", lw=0.8)
    ax.set_ylim(min(shown + [limit.lsr_limit(span[0])]) / 1.5, max(shown) * 1.5)
    ax.set(yscale="log", xlim=span, xlabel="mtf_mean (band mean of the radial MTF)", ylabel=f"LSR ({p_label})",
           title="LSR against MTF; dotted: the floors; dashed: the physical limit")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    return fig
