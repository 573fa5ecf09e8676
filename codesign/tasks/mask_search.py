"""``+experiment=mask_search``: nlopt search of a half-ring mask's r_n, theta_n for the lowest LSR under an MTF
floor, plus a Pareto sweep over floors; writes evaluations.csv, best_mask.json, metrics.json, figures and
TensorBoard events into the run dir."""
from __future__ import annotations

import csv
import io as _stringio
import logging
import math
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from codesign.config.runtime import resolve_dtype
from codesign.design.monitor import MaskMonitor, published_reference
from codesign.design.search import MaskObjective, best_point, run_start, start_points
from codesign.design.search_spec import SearchSpec
from codesign.io import files as io, plots
from codesign.io.tensorboard import open_writer, tensorboard_enabled
from codesign.errors import ConfigError
from codesign.optics import OpticalSystem, OpticsSpec, build_mask, circular_mtf, metrics
from codesign.optics.masks import PUBLISHED_R

log = logging.getLogger("codesign.mask_search")


# Root keys this experiment reads besides the common ones (conf/experiment/mask_search.yaml); any other is refused.
ROOT_KEYS: tuple[str, ...] = ("search",)

def _set_mask(mask, x: np.ndarray) -> None:
    n = mask.r.numel()
    x = np.array(x, dtype=np.float64)
    with torch.no_grad():
        mask.r.copy_(torch.from_numpy(x[:n]))
        mask.theta.copy_(torch.from_numpy(x[n:]))


def _x_of(mask) -> np.ndarray:
    return torch.cat([mask.r.detach(), mask.theta.detach()]).double().cpu().numpy()


def _check_floor(key: str, value, floor: float, uncoded: float, published: float) -> None:
    # |OTF| of a phase-only pupil is at most the uncoded aperture's (triangle inequality on the autocorrelation),
    # so a floor at or above the uncoded mtf_mean cannot be met by any r_n, theta_n: refuse before searching.
    if not floor < uncoded:
        raise ConfigError(key, value, f"gives the MTF floor {floor:.4g}, at or above the uncoded aperture's mtf_mean "
                          f"{uncoded:.4g}, which no phase mask can reach: mtf_floor x factor must be below "
                          f"{uncoded:.4g} (the published mask's mtf_mean is {published:.4g})")


def _search_floor(system, mask, monitor, s: SearchSpec, floor: float, factor: float, starts, max_evals: int,
                  bounds: tuple[np.ndarray, np.ndarray], writer, tag: str, energy_floor: float | None) -> dict:
    """Every start of one floor (``energy_floor``: floor on the window energy, None = off); returns {factor,
    floor, objective (with the evaluation log), starts, seconds}."""
    t0 = time.perf_counter()

    def on_eval(obj: MaskObjective, ev) -> None:
        k = len(obj.records)
        if writer is not None:
            writer.add_scalar(f"{tag}/lsr_smooth", ev.lsr_smooth, k)
            writer.add_scalar(f"{tag}/mtf_mean", ev.mtf_mean, k)
            if obj.best is not None:
                writer.add_scalar(f"{tag}/best_lsr_smooth", obj.best.lsr_smooth, k)
        if k % s.log_every == 0:
            best = (f"{obj.best.lsr_smooth:.4g} (mtf_mean {obj.best.mtf_mean:.4g})" if obj.best else
                    f"none yet (closest mtf_mean {obj.least_violating.mtf_mean:.4g})")
            log.info("floor %.4g: start %s eval %d (%d in all): best feasible lsr_smooth %s, %.2f evals/s", floor,
                     obj.label, obj.start_evals, k, best, k / (time.perf_counter() - t0))

    obj = MaskObjective(system, mask, monitor.radial, s.mtf_band, s.lsr_p, floor, on_eval, energy_floor)
    results = []
    for label, kind, x0 in starts:
        res = {"init": kind, **run_start(obj, label, x0, *bounds, s.algorithm, s.local_algorithm, max_evals,
                                         s.polish_max_evals, s.xtol_rel, s.ftol_rel)}
        results.append(res)
        log.info("floor %.4g: start %s (%s) %s after %d evaluations: %s", floor, label, kind, res["result"],
                 res["evaluations"], f"lsr_smooth {res['lsr_smooth']:.4g}, mtf_mean {res['mtf_mean']:.4g}"
                 if res["feasible"] else f"no feasible point (violation {res['min_violation']:.3g})")
    return {"factor": factor, "floor": floor, "objective": obj, "starts": results,
            "seconds": time.perf_counter() - t0, "evaluations": len(obj.records)}


def _write_evaluations(path: Path, sweeps: list[dict], n: int) -> None:
    buf = _stringio.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["floor_factor", "mtf_floor", "start", "eval", *[f"r_{i + 1}" for i in range(n)],
                *[f"theta_{i + 1}" for i in range(n)], "lsr_smooth", "mtf_mean", "window_energy", "feasible"])
    for sw in sweeps:
        for label, k, ev in sw["objective"].records:
            w.writerow([sw["factor"], sw["floor"], label, k, *ev.x.tolist(), ev.lsr_smooth, ev.mtf_mean, ev.energy,
                        int(ev.feasible)])
    io.atomic_write_bytes(path, lambda f: f.write(buf.getvalue().encode()))


def pareto_figure(sweeps: list[dict], front: list[dict], base: dict, p: float):
    """Smooth LSR (log) against mtf_mean: every evaluation (darker: feasible under its own run's floor), the best
    point per floor (over all evaluations), the published mask."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.6, 4.6))
    evs = [ev for sw in sweeps for _, _, ev in sw["objective"].records]
    for feasible, colour, label in ((False, "0.85", "other evaluations"), (True, "0.55", "feasible evaluations")):
        pts = np.array([(ev.mtf_mean, ev.lsr_smooth) for ev in evs if ev.feasible == feasible]).reshape(-1, 2)
        ax.scatter(pts[:, 0], pts[:, 1], s=5, c=colour, label=label + " (under their run's floor)" * feasible)
    ok = sorted((f for f in front if f["feasible"]), key=lambda f: f["mtf_floor"])
    for f in front:
        ax.axvline(f["mtf_floor"], color="C0", ls=":", lw=0.8)
    if ok:
        ax.plot([f["mtf_mean"] for f in ok], [f["lsr_smooth"] for f in ok], "o-", color="C0", label="best per floor")
        ax.plot([f["mtf_mean"] for f in ok], [f["lsr"] for f in ok], "s", mfc="none", color="C0",
                label="its hard LSR (refined peak)")
        labels: dict[tuple[float, float], list[str]] = {}  # one label per point: several floors can share a best
        for f in ok:
            labels.setdefault((f["mtf_mean"], f["lsr_smooth"]), []).append(f"{f['factor']:g}")
        for xy, names in labels.items():
            ax.annotate("x" + ", ".join(names), xy, textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.plot([base["mtf_mean"]], [base["lsr_smooth"]], "*", ms=14, color="C3", label="published mask")
    # random starts reach LSR ~ 1; keep the axis on the interesting range (feasible points and the baseline)
    shown = [ev.lsr_smooth for ev in evs if ev.feasible] + [base["lsr_smooth"]]
    ax.set_ylim(min(shown + [ev.lsr_smooth for ev in evs]) / 1.3, max(shown) * 1.5)
    ax.set(yscale="log", xlabel="mtf_mean (band mean of the radial MTF)", ylabel=f"smooth LSR (p = {p:g})",
           title="LSR against MTF; dotted: the floors")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return fig


def run(cfg: DictConfig, run_dir: Path, device: torch.device) -> float:
    s = SearchSpec.from_config(OmegaConf.to_container(cfg.get("search") or OmegaConf.create({}), resolve=True))
    spec = OpticsSpec.from_config(OmegaConf.to_container(cfg.optics, resolve=True))
    mask_cfg = OmegaConf.to_container(cfg.mask, resolve=True)
    if mask_cfg.get("kind") != "halfring":
        raise ConfigError("mask.kind", mask_cfg.get("kind"), "mask_search optimizes the radii and angles of a "
                          "half-ring mask: use mask=halfring")
    system = OpticalSystem(spec, dtype=resolve_dtype("search.precision", s.precision), device=device)
    mask = build_mask(mask_cfg, system.grid, spec.aperture_diameter_m)
    # The baseline shares the configured convention, orders and signs: only r_n, theta_n differ.
    published = published_reference(mask_cfg, system)
    n = mask.r.numel()
    lower = np.array([s.r_bounds[0]] * n + [s.theta_bounds[0]] * n)
    upper = np.array([s.r_bounds[1]] * n + [s.theta_bounds[1]] * n)
    init_x = None
    if s.init == "published":
        if n != len(PUBLISHED_R):
            raise ConfigError("search.init", s.init, f"the configured mask has {n} rings, the published one "
                              f"{len(PUBLISHED_R)}: use search.init=mask or random")
        init_x = _x_of(published)
    elif s.init == "mask":
        init_x = _x_of(mask)
    if init_x is not None and not np.array_equal(np.clip(init_x, lower, upper), init_x):
        log.warning("search.init=%s lies outside search.r_bounds / theta_bounds; start 0 is clipped into them", s.init)
        init_x = np.clip(init_x, lower, upper)

    monitor = MaskMonitor(system, published, s.mtf_band, s.lsr_p)
    base, base_arr = monitor.measure(published, refine=True)
    energy_floor = s.energy_floor_value(float(base_arr["psf"].sum()))
    with torch.no_grad():
        psf0 = system.uncoded_psf()
        rad0 = monitor.radial(metrics.mtf(psf0))
        mean0 = float(monitor.radial.summary(rad0, s.mtf_band)[0])
    floor_key = "search.mtf_floor_factor" if s.mtf_floor == "published" else "search.mtf_floor"
    floor = s.floor_value(base["mtf_mean"])
    _check_floor(floor_key, s.mtf_floor_factor if s.mtf_floor == "published" else s.mtf_floor, floor, mean0,
                 base["mtf_mean"])
    for i, f in enumerate(s.pareto_factors or ()):
        _check_floor(f"search.pareto_factors[{i}]", f, s.floor_value(base["mtf_mean"], f), mean0, base["mtf_mean"])
    log.info("%s on %d variables, %d starts x %d evaluations, mtf_mean >= %.4g (published %.4g x %g), published "
             "LSR %.4g; pupil %d, window %d, %s", s.algorithm, 2 * n, s.starts, s.max_evals, floor, base["mtf_mean"],
             s.mtf_floor_factor, base["lsr"], spec.grid_n, spec.focal_n, system.dtype)

    writer = open_writer(run_dir, tensorboard_enabled(cfg))
    bounds = (lower, upper)
    try:
        starts = start_points(s.init, init_x, s.seed, lower, upper, s.starts)
        main = _search_floor(system, mask, monitor, s, floor, s.mtf_floor_factor, starts, s.max_evals, bounds,
                             writer, "search", energy_floor)
        sweeps = [main]
        _write_evaluations(run_dir / "evaluations.csv", sweeps, n)
        front_sweeps = []
        for f in s.pareto_factors or ():
            if math.isclose(f, s.mtf_floor_factor, rel_tol=1e-9):
                front_sweeps.append(main)
                continue
            warm = best_point([main], floor)[0].x  # the main search's best: a good start for nearby floors
            pts = start_points(s.init, init_x, s.seed, lower, upper, s.pareto_starts, warm=warm)
            sw = _search_floor(system, mask, monitor, s, s.floor_value(base["mtf_mean"], f), f, pts,
                               s.pareto_max_evals, bounds, writer, f"pareto_x{f:g}", energy_floor)
            sweeps.append(sw)
            front_sweeps.append(sw)
            _write_evaluations(run_dir / "evaluations.csv", sweeps, n)
        front = []
        for sw in front_sweeps:
            ev, ok, found = best_point(sweeps, sw["floor"])
            _set_mask(mask, ev.x)
            v, _ = monitor.measure(mask, refine=True)
            front.append({"factor": sw["factor"], "mtf_floor": sw["floor"], "feasible": ok, "found_at_factor": found,
                          "lsr": v["lsr"], "lsr_smooth": v["lsr_smooth"], "mtf_mean": v["mtf_mean"], "bsr": v["bsr"],
                          "evaluations": sw["evaluations"], "seconds": sw["seconds"], **mask.summary()})
            log.info("pareto: floor x%g = %.4g: %s lsr %.4g (smooth %.4g), mtf_mean %.4g, bsr %.3f", sw["factor"],
                     sw["floor"], "feasible" if front[-1]["feasible"] else "INFEASIBLE", v["lsr"], v["lsr_smooth"],
                     v["mtf_mean"], v["bsr"])

        chosen, feasible, found = best_point(sweeps, floor)
        _set_mask(mask, chosen.x)
        values, arrays = monitor.measure(mask, refine=True)
        values["found_at_factor"] = found
        violation = 0.0 if feasible else floor - chosen.mtf_mean
        if not feasible:
            log.error("NO FEASIBLE POINT: in %d evaluations (%d starts) mtf_mean never reached the floor %.4g "
                      "(closest %.4g, violation %.3g = %.2f%% of the floor); the outputs describe that closest point",
                      sum(sw["evaluations"] for sw in sweeps), s.starts, floor, chosen.mtf_mean, violation,
                      100 * violation / floor)
        if values["bsr"] < base["bsr"] - 0.1:
            # Light sent beyond the focal window is invisible to both the LSR and the (window) MTF. Measured: a mask
            # 2.9x better than the published one on the 640 window was 1.5x better, and under the MTF floor, on 1280.
            log.warning("the best mask keeps %.2f of the energy in the focal window (published mask: %.2f): part of "
                        "its gain may be light (and peaks) pushed outside the window; re-measure it on a wider one "
                        "(+experiment=psf mask.init=%s optics.focal_n=...)", values["bsr"], base["bsr"],
                        run_dir / "best_mask.json")
        uncoded = {"psf": psf0, "mtf_radial": rad0, "mtf_mean": mean0, "freqs": monitor.radial.freqs}
        out = _outputs(run_dir, s, system, mask, (values, arrays), (base, base_arr), uncoded, floor, feasible,
                       violation, main, sweeps, front, device)
        if writer is not None:
            total = sum(sw["evaluations"] for sw in sweeps)
            monitor.log(writer, 0, published, prefix="published")
            monitor.log(writer, total, mask, prefix="best")
            writer.add_hparams({"algorithm": s.algorithm, "local_algorithm": str(s.local_algorithm), "init": s.init,
                                "starts": s.starts, "max_evals": s.max_evals, "mtf_floor_factor": s.mtf_floor_factor,
                                "lsr_p": s.lsr_p, "precision": s.precision, "seed": s.seed},
                               {f"hparam/{k}": float(out[k]) for k in ("lsr", "lsr_smooth", "mtf_mean", "feasible",
                                                                       "evaluations", "evals_per_second")},
                               run_name="hparams")
    finally:
        if writer is not None:
            writer.close()
    log.info("best: lsr %.4g (smooth %.4g, published %.4g), mtf_mean %.4g >= %.4g: %s; %d evaluations in %.1f s "
             "(%.2f/s); wrote %s", values["lsr"], values["lsr_smooth"], base["lsr"], values["mtf_mean"], floor,
             "feasible" if feasible else "INFEASIBLE", main["evaluations"], main["seconds"], out["evals_per_second"],
             run_dir)
    return values["lsr"] if feasible else float("nan")


def _outputs(run_dir: Path, s: SearchSpec, system, mask, best: tuple[dict, dict], baseline: tuple[dict, dict],
             uncoded: dict, floor: float, feasible: bool, violation: float, main: dict, sweeps: list[dict],
             front: list[dict], device) -> dict:
    """best_mask.json, metrics.json and the figures; returns the metrics. ``best``, ``baseline``: (scalars, arrays)
    of the best and the published mask (monitor.measure); ``uncoded``: psf, mtf_radial, mtf_mean, freqs."""
    spec = system.spec
    (values, arrays), (base, base_arr) = best, baseline
    mean0 = uncoded["mtf_mean"]
    summary = mask.summary()
    io.write_json(run_dir / "best_mask.json", {
        **mask.record(), "lsr": values["lsr"], "lsr_smooth": values["lsr_smooth"],
        "mtf_mean": values["mtf_mean"], "mtf_floor": floor, "feasible": feasible, "bsr": values["bsr"]})
    out = {
        "lsr": values["lsr"], "lsr_smooth": values["lsr_smooth"], "lsr_sampled": values["lsr_sampled"],
        "mtf_mean": values["mtf_mean"], "mtf_min": values["mtf_min"], "bsr": values["bsr"],
        "lsr_baseline": base["lsr"], "lsr_smooth_baseline": base["lsr_smooth"], "mtf_mean_baseline": base["mtf_mean"],
        "mtf_min_baseline": base["mtf_min"], "mtf_mean_uncoded": mean0, "lsr_vs_baseline": values["lsr"] / base["lsr"],
        "mtf_floor": floor, "mtf_floor_factor": s.mtf_floor_factor, "mtf_floor_source": str(s.mtf_floor),
        "window_energy": float(arrays["psf"].sum()), "window_energy_baseline": float(base_arr["psf"].sum()),
        "window_energy_floor": s.energy_floor_value(float(base_arr["psf"].sum())),
        "feasible": feasible, "found_at_factor": values["found_at_factor"], "min_violation": violation,
        "min_violation_rel": violation / floor, **summary,
        "evaluations": main["evaluations"], "seconds": main["seconds"],
        "evals_per_second": main["evaluations"] / max(main["seconds"], 1e-12),
        "evaluations_total": sum(sw["evaluations"] for sw in sweeps),
        "algorithm": s.algorithm, "local_algorithm": s.local_algorithm, "init": s.init, "n_starts": s.starts,
        "max_evals": s.max_evals, "seed": s.seed, "lsr_p": s.lsr_p, "mtf_band_low": s.mtf_band[0],
        "mtf_band_high": s.mtf_band[1], "r_bounds": list(s.r_bounds), "theta_bounds": list(s.theta_bounds),
        "starts": main["starts"], "pareto": front,
        "pupil_n": spec.grid_n, "pupil_pitch_m": spec.pupil_pitch_m, "focal_n": spec.focal_n,
        "focal_pitch_m": spec.focal_pitch_m, "propagator": system.method, "precision": s.precision,
        "device": str(device), "threads": torch.get_num_threads(),
    }
    io.write_json(run_dir / "metrics.json", out)

    ap = system.grid.aperture.cpu().numpy()
    np_ = lambda t: t.detach().cpu().numpy()  # noqa: E731
    tag = "" if feasible else " (INFEASIBLE: closest point)"
    for name, v, arr in (("", values, arrays), ("published_", base, base_arr)):
        who = "best" if name == "" else "published"
        io.save_figure(run_dir / f"{name}phase.png", plots.phase_figure(
            np_(arr["phase"]), ap, spec.pupil_pitch_m, f"{who} half-ring mask ({mask.convention})"
            + (tag if name == "" else "")))
        io.save_figure(run_dir / f"{name}psf_log.png", plots.psf_figure(
            np_(arr["psf"]), np_(uncoded["psf"]), spec.focal_pitch_m, f"{who} mask: LSR = {v['lsr']:.3g}, "
            f"mtf_mean = {v['mtf_mean']:.3g}"))
    freqs = np_(uncoded["freqs"])
    analytic = circular_mtf(torch.from_numpy(freqs)).numpy()
    io.save_figure(run_dir / "mtf.png", plots.mtf_figure(
        freqs, {"best mask": np_(arrays["mtf_radial"]), "published mask": np_(base_arr["mtf_radial"]),
                "uncoded": np_(uncoded["mtf_radial"]), "analytic circular pupil": analytic},
        s.mtf_band, f"MTF: best mean {values['mtf_mean']:.3g}, published {base['mtf_mean']:.3g}, floor {floor:.3g}"))
    io.save_figure(run_dir / "pareto.png", pareto_figure(sweeps, front, base, s.lsr_p))
    return out
