"""``+experiment=tolerance mask.init=PATH``: the design exported as ``+experiment=export`` would (the same
``export`` and ``material`` settings), then Monte Carlo over fabrication and assembly errors (codesign/fab/
tolerance.py): each source alone (its LSR distribution and its effect at +-1 sigma) and all at once (the yield:
the fraction of plates whose LSR stays below ``tolerance.lsr_ceiling``)."""
from __future__ import annotations

import csv
import io as _io
import logging
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from codesign.config.runtime import to_container
from codesign.fab.plate_setup import build_plate
from codesign.fab.plate_figures import sigma_text, tolerance_figure
from codesign.fab.tolerance import SOURCES, Errors, PlateEvaluator, ToleranceSpec, deterministic, draw
from codesign.io import files as io
from codesign.optics import OpticalSystem
from codesign.experiments.specs import metrics_spec, plate_settings
from codesign.experiments.protocol import Experiment
from codesign.signals import Interrupted

log = logging.getLogger("codesign.tolerance")


EXPERIMENT = Experiment(
    summary="Monte Carlo fabrication and assembly tolerance (yield) of a design",
    first_work="OpticalSystem",
    root_keys=("precision", "export", "tolerance"),
    reads=("optics", "material", "mask", "metrics"),
    outputs=("metrics.json", "samples.csv", "tolerance.png"),
    smoke={"export.pitch_m": 8.0e-6, "tolerance.samples": 16, "tolerance.samples_per_source": 4},
)
# the samples of the sources that finished when SIGINT / SIGTERM stopped the Monte Carlo (a finished run removes it)
PARTIAL_SAMPLES = "samples.partial.csv"


class _Progress:
    """A progress line every ~10 s: samples done of the total, rate, ETA."""

    def __init__(self, total: int):
        self.total, self.done, self.t0, self.last = total, 0, time.perf_counter(), time.perf_counter()

    def __call__(self, k: int) -> None:
        self.done += k
        now = time.perf_counter()
        if now - self.last >= 10 or self.done == self.total:
            rate = self.done / max(now - self.t0, 1e-9)
            log.info("%d / %d samples (%.1f/s, ETA %.0f s)", self.done, self.total, rate,
                     (self.total - self.done) / max(rate, 1e-9))
            self.last = now


def _stats(lsr: torch.Tensor, mtf: torch.Tensor, ceiling: float) -> dict:
    x = lsr.numpy()
    return {"lsr_mean": float(x.mean()), "lsr_std": float(x.std()), "lsr_p05": float(np.percentile(x, 5)),
            "lsr_p95": float(np.percentile(x, 95)), "lsr_max": float(x.max()), "mtf_mean_mean": float(mtf.mean()),
            "mtf_mean_std": float(mtf.std(unbiased=False)), "yield": float((lsr <= ceiling).double().mean())}


def _per_source(ts, active, plate, evaluate, gen, ceiling, progress, out) -> None:
    """Each active source alone: its samples and its +-1 sigma points, appended to ``out`` = (rows, per_source,
    dist) as each source finishes."""
    rows, per_source, dist = out
    for source in active:
        e = draw(ts, (source,), ts.samples_per_source, plate.n_levels, gen)
        lsr, mtf = evaluate(e, progress) if len(e) else (torch.zeros(0), torch.zeros(0))
        stats = _stats(lsr, mtf, ceiling) if len(e) else {}
        for sign, name in ((1, "plus"), (-1, "minus")):
            d = deterministic(ts, source, sign, plate.n_levels)
            if d is not None:
                at_lsr, at_mtf = evaluate(d)
                stats[f"lsr_at_{name}_1sigma"] = float(at_lsr[0])
                stats[f"mtf_mean_at_{name}_1sigma"] = float(at_mtf[0])
        per_source[source] = {"sigma": ts.sigma(source), **stats}
        dist[source] = lsr.numpy()
        rows += [(source, e, lsr, mtf)]


def _write_samples(path: Path, rows) -> None:
    """samples.csv: one line per sample (its errors, LSR and mtf_mean), written atomically."""
    buf = _io.StringIO()
    w = csv.writer(buf)
    cols = list(Errors.zeros(1, None).columns())
    w.writerow(["source", "sample", *cols, "lsr", "mtf_mean"])
    for source, e, lsr, mtf in rows:
        table = e.columns()
        for i in range(len(e)):
            w.writerow([source, i, *(f"{float(table[c][i]):.6g}" for c in cols), f"{float(lsr[i]):.6g}",
                        f"{float(mtf[i]):.6g}"])
    io.atomic_write_bytes(path, lambda fh: fh.write(buf.getvalue().encode()))


def _interrupted(stop: Interrupted, run_dir: Path, rows, progress: _Progress) -> Interrupted:
    """SIGINT / SIGTERM during the Monte Carlo: the samples of the sources that finished kept in
    samples.partial.csv (never samples.csv: a finished analysis's); the Interrupted to report."""
    where = f"the Monte Carlo stopped after {progress.done} of {progress.total} samples"
    if not rows:
        return Interrupted(stop.signum, f"{where}; no source had finished: no sample to keep")
    _write_samples(run_dir / PARTIAL_SAMPLES, rows)
    sources = ", ".join(source for source, *_ in rows)
    return Interrupted(stop.signum, f"{where}; the samples of the sources that finished ({sources}) in "
                                    f"{run_dir / PARTIAL_SAMPLES} (partial: no yield)")


def run(cfg: DictConfig, run_dir: Path, device: torch.device) -> float:
    """The plate of the configured design under fabrication and assembly errors: each source alone, then every
    source at once (Monte Carlo of tolerance.*), the LSR and mtf_mean of each sample; writes samples.csv,
    tolerance.png and metrics.json (an interrupted run keeps the finished sources in samples.partial.csv); returns
    the yield (the share of plates with LSR under the ceiling). Steps: build, Monte Carlo, report."""
    spec, ex, material, mask_cfg, dtype = plate_settings(cfg)
    ts = ToleranceSpec.from_config(to_container(cfg.get("tolerance")))
    ts.check_detuning(spec)  # every detuned sample a wavelength the window carries, before any work
    band = metrics_spec(cfg).mtf_band
    material.check_wavelength(spec.wavelength_m)
    system = OpticalSystem(spec, dtype=dtype, device=device)
    plate = build_plate(mask_cfg, spec, ex, material)
    gen = torch.Generator().manual_seed(ts.seed)
    evaluate = PlateEvaluator(plate, system, material, band, gen, ts.batch)
    active = tuple(s for s in SOURCES if ts.sigma(s) > 0)
    nominal = tuple(float(v[0]) for v in evaluate(Errors.zeros(1, plate.n_levels)))
    ceiling = ts.ceiling(nominal[0])
    log.info("plate %d x %d at %.3g m (%s); nominal LSR %.4g (sampled peak), mtf_mean %.4g; yield ceiling LSR "
             "<= %.4g; sources: %s", plate.n, plate.n, plate.pitch,
             f"{plate.n_levels} levels" if plate.n_levels else "continuous", nominal[0], nominal[1], ceiling,
             ", ".join(f"{s} {ts.sigma(s):.3g}" for s in active) or "none")
    rows, per_source, dist, overall, progress = _monte_carlo(run_dir, ts, active, plate, evaluate, gen, ceiling)
    _report(run_dir, ts, plate, material, mask_cfg["kind"], nominal, ceiling, rows, dist, per_source, overall,
            active, progress)
    return overall["yield"]


def _monte_carlo(run_dir: Path, ts, active: tuple, plate, evaluate, gen, ceiling: float) -> tuple:
    """Each active source alone (samples_per_source), then every source at once (samples), drawn from ``gen``:
    (rows of samples.csv, the per-source statistics, the LSR distributions, the overall statistics, the progress);
    an interrupt keeps the sources that finished."""
    progress = _Progress(ts.samples_per_source * len(active) + ts.samples)
    rows, per_source, dist = [], {}, {}  # filled source by source: what an interrupt keeps
    try:
        _per_source(ts, active, plate, evaluate, gen, ceiling, progress, (rows, per_source, dist))
        combined = draw(ts, active, ts.samples, plate.n_levels, gen)
        lsr_all, mtf_all = evaluate(combined, progress)
    except Interrupted as stop:
        raise _interrupted(stop, run_dir, rows, progress) from None
    dist["all sources"] = lsr_all.numpy()
    rows.append(("all", combined, lsr_all, mtf_all))
    return rows, per_source, dist, _stats(lsr_all, mtf_all, ceiling), progress


def _report(run_dir: Path, ts, plate, material, kind: str, nominal: tuple[float, float], ceiling: float, rows,
            dist: dict, per_source: dict, overall: dict, active: tuple, progress) -> None:
    """samples.csv, tolerance.png, metrics.json and the log's table of the sources."""
    nominal_lsr, nominal_mtf = nominal
    _write_samples(run_dir / "samples.csv", rows)
    (run_dir / PARTIAL_SAMPLES).unlink(missing_ok=True)  # an earlier interrupted run's: this one finished
    io.save_figure(run_dir / "tolerance.png", tolerance_figure(
        dist, nominal_lsr, ceiling, f"{kind} plate, {material.name}: LSR under fabrication and assembly "
        f"errors (nominal {nominal_lsr:.4g})", sigmas={**{src: sigma_text(src, ts.sigma(src)) for src in active},
                                                      "all sources": "every source at its sigma"},
        ceiling_rule="1.2 x nominal" if ts.lsr_ceiling == "auto" else "tolerance.lsr_ceiling"))
    metrics = {"nominal_lsr": nominal_lsr, "nominal_mtf_mean": nominal_mtf, "lsr_ceiling": ceiling,
               "yield": overall["yield"], "samples": ts.samples, "samples_per_source": ts.samples_per_source,
               "all_sources": overall, "sources": per_source, "levels": plate.n_levels, "pitch_m": plate.pitch,
               "material": material.name, "mask_kind": kind, "seconds": time.perf_counter() - progress.t0}
    io.write_json(run_dir / "metrics.json", metrics)
    for source, v in per_source.items():
        log.info("%-12s sigma %-9.3g LSR mean %.4g std %.3g p95 %.4g; at +1 sigma %s; yield %.1f%%", source,
                 v["sigma"], v.get("lsr_mean", float("nan")), v.get("lsr_std", float("nan")),
                 v.get("lsr_p95", float("nan")),
                 f"{v['lsr_at_plus_1sigma']:.4g}" if "lsr_at_plus_1sigma" in v else "random (see spread)",
                 100 * v.get("yield", float("nan")))
    log.info("all sources at once (%d samples): LSR mean %.4g, p95 %.4g; yield %.1f%% at LSR <= %.4g; %.0f s",
             ts.samples, overall["lsr_mean"], overall["lsr_p95"], 100 * overall["yield"], ceiling, metrics["seconds"])
    log.info("wrote %s", run_dir)
