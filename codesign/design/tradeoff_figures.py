"""Figures of the design: LSR against mtf_mean with the physical limit curve (a search's evaluations and fronts,
or several families' fronts side by side)."""
from __future__ import annotations

import numpy as np

from codesign.io.plots import plt


def fit_span(values, pad: float = 0.08) -> tuple[float, float]:
    """An axis range that holds ``values`` with a margin of ``pad`` of their range on each side (a tenth of the
    value itself when they all coincide); (0.01, 0.1) when there are none."""
    vals = [float(v) for v in values if v is not None and np.isfinite(v)]
    if not vals:
        return 0.01, 0.1
    lo, hi = min(vals), max(vals)
    margin = pad * (hi - lo) if hi > lo else 0.1 * abs(hi) or 0.01
    return max(lo - margin, 0.0), hi + margin


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
    span = fit_span(xs + list(floors or ()))
    limit_line(ax, limit, span)
    markers = "os^Dvp<>h"
    for i, (name, pts) in enumerate(points.items()):
        if pts:  # distinct markers too: designs of different families can land on the same point
            arr = np.array(sorted(pts))
            ax.plot(arr[:, 0], arr[:, 1], markers[i % len(markers)] + ("-" if len(arr) > 1 else ""), ms=5,
                    color=f"C{i}", mfc="none", label=name)
    for j, (name, (m, v)) in enumerate(references.items()):  # references in black / greys, apart from the series
        ax.plot([m], [v], "*", ms=13, color=str(0.45 * j), label=name)
    for i, f in enumerate(floors or ()):
        ax.axvline(f, color="0.6", ls=":", lw=0.8, label="MTF floors" if i == 0 else None)
    if ys:
        ax.set_ylim(min(min(ys), limit.lsr_limit(span[0])) / 1.5, max(ys) * 1.8)
    ax.set(yscale="log", xlim=span, xlabel="mtf_mean (band mean of the radial MTF, 0..1)",
           ylabel="LSR (peak / uncoded peak)", title=title)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    return fig


def evaluations_figure(sweeps, front: list[dict], base: dict, limit, p_label: str, best: dict | None = None,
                       best_label: str = "searched design"):
    """A search's evaluations (sampled LSR against mtf_mean; darker: feasible under their floor), the best point per
    floor, the searched design ``best`` (its mtf_mean and continuous-peak lsr; feasible or not), the published mask
    and the limit curve; the x axis fitted to what is drawn."""
    fig, ax = plt.subplots(figsize=(6.8, 4.8))
    evs = [ev for sw in sweeps for ev in sw.problem.records]
    for feasible, colour, label in ((False, "0.85", "other evaluations"), (True, "0.55", "feasible evaluations")):
        pts = np.array([(ev.mtf_mean, ev.lsr_sampled) for ev in evs if ev.feasible == feasible]).reshape(-1, 2)
        if len(pts):  # no entry in the legend for a series with nothing to show
            ax.scatter(pts[:, 0], pts[:, 1], s=4, c=colour, label=f"{label} ({len(pts)})")
    ok = sorted((f for f in front if f["feasible"]), key=lambda f: f["mtf_floor"] or 0)
    if best is not None and len(ok) == 1 and np.isclose(ok[0]["lsr"], best["lsr"]) \
            and np.isclose(ok[0]["mtf_mean"], best["mtf_mean"]):
        ok = []  # one floor whose best is the searched design: drawn once, as the design
    if ok:
        ax.plot([f["mtf_mean"] for f in ok], [f["lsr"] for f in ok], "o-" if len(ok) > 1 else "o", color="C0",
                mfc="none", label="best per floor (continuous peak)")
    if best is not None:
        ax.plot([best["mtf_mean"]], [best["lsr"]], "D", ms=7, color="C2", mec="k", zorder=4,
                label=f"{best_label}: LSR {best['lsr']:.3g}, mtf_mean {best['mtf_mean']:.3g}")
    ax.plot([base["mtf_mean"]], [base["lsr"]], "*", ms=14, color="C3", zorder=3,
            label=f"published mask: LSR {base['lsr']:.3g}, mtf_mean {base['mtf_mean']:.3g}")
    shown = [f["lsr"] for f in ok] + [base["lsr"]] + [ev.lsr_sampled for ev in evs] + \
        ([best["lsr"]] if best is not None else [])
    floors = sorted({f["mtf_floor"] for f in front if f["mtf_floor"]})
    mtfs = [ev.mtf_mean for ev in evs] + [base["mtf_mean"]] + floors + ([best["mtf_mean"]] if best else [])
    span = fit_span(mtfs)
    limit_line(ax, limit, span)
    for i, f in enumerate(floors):
        ax.axvline(f, color="C0", ls=":", lw=0.8, label="MTF floor (constraint)" if i == 0 else None)
    shown = [v for v in shown if np.isfinite(v) and v > 0]
    ax.set_ylim(min(shown + [limit.lsr_limit(max(span[0], 1e-4))]) / 1.5, max(shown) * 1.5)
    ax.set(yscale="log", xlim=span, xlabel="mtf_mean (band mean of the radial MTF, 0..1)",
           ylabel=f"LSR ({p_label}; peak / uncoded peak)", title="LSR against MTF of the search's evaluations")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    return fig
