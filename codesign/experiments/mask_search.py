"""``+experiment=mask_search``: search the configured mask family's parameters (nlopt, or AL_LBFGS for large
vectors) for the lowest LSR under the MTF and window-energy floors (or the best restorability under an LSR
ceiling), sweep the floor, re-check the best design on a finer pupil grid and a window that holds its PSF, and
write evaluations.csv, best_mask.json (mask.init=PATH), metrics.json, figures and TensorBoard events."""
from __future__ import annotations

import csv
import io as _stringio
import logging
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import DictConfig

from codesign.config.runtime import resolve_dtype, tensorboard_enabled, to_container
from codesign.camera import build_sensor_spec
from codesign.data.scenes import build_scene_source
from codesign.design.check import report_sampling, sampling_of, sampling_report, verify_design
from codesign.design.tradeoff_figures import evaluations_figure
from codesign.design.limits import MTFLimit
from codesign.design.merit import MaskMonitor, MetricsSpec, published_reference
from codesign.design.problem import DesignProblem, Limits
from codesign.optics.masks.base import PhaseFitSpec
from codesign.optics.masks.records import write_record
from codesign.design.search import MaskSearch, start_points
from codesign.design.search_spec import SearchSpec
from codesign.design.search_setup import (quantized_figures, restorability_tools, search_limits, start_init,
                                   start_vector)
from codesign.errors import ConfigError
from codesign.fab.laser_lines import lines_summary, log_lines, run_lines, surface_name
from codesign.io import files as io, plots
from codesign.io.tensorboard import open_writer
from codesign.optics import OpticalSystem, OpticsSpec, RadialMTF, build_mask, circular_mtf, metrics
from codesign.optics.lines import smooth_lsr
from codesign.experiments.specs import material_of, metrics_spec
from codesign.experiments.protocol import Experiment
from codesign.signals import Interrupted

log = logging.getLogger("codesign.mask_search")


EXPERIMENT = Experiment(
    summary="mask-only search of any family (nlopt), re-checked on a finer grid and a whole-PSF window",
    first_work="MaskSearch.run",
    root_keys=("search",),
    reads=("optics", "material", "mask", "sensor", "data", "metrics"),
    outputs=("metrics.json", "best_mask.json", "evaluations.csv", "mtf.png", "pareto.png"),
    smoke={"search.max_evals": 8, "search.starts": 2, "search.polish_max_evals": 4, "search.pareto_factors": [1.0],
           "search.pareto_max_evals": 4},
)
# an interrupted search's best point (SIGINT / SIGTERM): a record marked "partial": true with its "stop_reason",
# under its own name so that nothing takes it for best_mask.json; a finished search removes it
PARTIAL_RECORD = "best_mask.partial.json"


def run(cfg: DictConfig, run_dir: Path, device: torch.device) -> float:
    """The search of search.* over the configured mask family's parameter vector, from the published mask's
    figures as the baseline; then the best design measured, re-checked and written (best_mask.json, metrics.json,
    evaluations.csv, figures); an interrupted search keeps its best point as a partial record. Returns the best
    design's certified LSR (NaN when infeasible). Steps: build, search, report."""
    job = _build(cfg, run_dir, device)
    search = job.search
    try:
        main = search.run()
        out = _outputs(job, main)
    except Interrupted as stop:
        raise _interrupted(stop, run_dir, search, job.mask, job.system.spec) from None
    finally:
        if search.writer is not None:
            search.writer.close()
    return out["lsr"] if out["feasible"] else float("nan")


@dataclass
class _Job:
    """A search and what its report needs: settings, optics, the searched mask, the published mask with its
    figures (the baseline), the MTF limit, the restorability tools, the laser lines (or None)."""

    s: SearchSpec
    ms: MetricsSpec
    run_dir: Path
    device: torch.device
    system: OpticalSystem
    mask: object
    published: object
    lines: object
    base: dict
    base_arr: dict
    limit: MTFLimit
    rest: object
    radial: RadialMTF
    search: MaskSearch | None = None


def _build(cfg: DictConfig, run_dir: Path, device: torch.device) -> _Job:
    """Settings, optics and mask, the published baseline and the search with its limits and starts."""
    s = SearchSpec.from_config(to_container(cfg.get("search")))
    ms = metrics_spec(cfg)
    spec = OpticsSpec.from_config(to_container(cfg.optics))
    mask_cfg = to_container(cfg.mask)
    system = OpticalSystem(spec, dtype=resolve_dtype("search.precision", s.precision), device=device)
    mask = build_mask(mask_cfg, system.grid, spec.aperture_diameter_m)
    s.check_size(mask.vector_size, mask.kind)  # an algorithm that cannot run this many parameters: refused now
    published = published_reference(mask_cfg, system)  # the same conventions: only the parameters differ
    lines = run_lines(material_of(cfg), system, "search.lsr_over" if s.lsr_over == "wavelengths" else None)
    monitor = MaskMonitor(system, published, ms.mtf_band, ms.lsr_p, ms.lsr_grids)
    base, base_arr = _published_figures(s, ms, monitor, published, lines)
    limit = MTFLimit(system, ms.mtf_band)
    sensor, source = build_sensor_spec(cfg), build_scene_source(cfg.data)
    rest = restorability_tools(sensor, source, system, mask, s.restorability_alpha_l)  # reported for every design
    base["restorability"] = rest.score(published)
    job = _Job(s, ms, run_dir, device, system, mask, published, lines, base, base_arr, limit, rest, monitor.radial)
    defocus = s.defocus_rad if s.defocus_rad is not None else mask_cfg.get("defocus_rad", PhaseFitSpec.defocus_rad)
    job.search = _search(job, open_writer(run_dir, tensorboard_enabled(cfg)), defocus)
    return job


def _published_figures(s: SearchSpec, ms, monitor, published, lines) -> tuple[dict, dict]:
    """The published mask's refined figures and arrays: the search's baseline (with search.lsr_over=wavelengths
    its sampled LSR is the worst line's, what a ceiling "published" means)."""
    base, base_arr = monitor.measure(published, refine=True)
    if s.lsr_over == "wavelengths":  # a ceiling "published" is the published mask's worst sampled line
        _, worst_sampled = smooth_lsr(monitor.system, published.phase().detach(), None, ms.lsr_p, ms.lsr_grids,
                                      published.plate_cell_m, lines)
        base["lsr_sampled"] = float(worst_sampled)
    return base, base_arr


def _search(job: _Job, writer, defocus: float) -> MaskSearch:
    """The MaskSearch of the job: its limits from the baseline, its start points, one DesignProblem per floor."""
    s, ms, system, mask, lines = job.s, job.ms, job.system, job.mask, job.lines
    n = mask.vector_size
    needs_restorability = s.objective == "restorability" or s.restorability_floor is not None
    limits = search_limits(s, mask, job.base, job.base_arr, job.limit, ms.lsr_p)
    init = start_init(s.init, mask)
    init_x = start_vector(init, mask, job.published, defocus)
    schedule = s.schedule(n, ms.lsr_p)
    lower, upper = (b.numpy() for b in mask.bounds())
    starts = start_points(init_x, init, s.resolved_starts(n), mask.random_vector, s.seed)
    radial = job.radial

    def make_problem(lim: Limits) -> DesignProblem:
        return DesignProblem(system, mask, radial, ms.mtf_band, s.objective, lim,
                             job.rest.pair if needs_restorability else None, lsr_grids=ms.lsr_grids,
                             lines=lines if s.lsr_over == "wavelengths" else None)

    search = MaskSearch(s, n, limits, make_problem, starts, mask.random_vector, (lower, upper), schedule, writer)
    log.info("%s search of a %s mask, %d parameters: %s, %d start(s) x %d evaluations, p %s; objective %s; "
             "constraints %s; published LSR %.4g, mtf_mean %.4g; pupil %d, window %d, %s%s", s.objective, mask.kind,
             n, search.algorithm, len(starts), search.max_evals, list(schedule), s.objective,
             {k: getattr(limits, k) for k in limits.active}, job.base["lsr"], job.base["mtf_mean"],
             system.spec.grid_n, system.spec.focal_n, system.dtype, "" if s.lsr_over == "design" else
             f"; LSR: the worst of the lines {[round(w * 1e9, 1) for w in lines.wavelengths]} nm "
             f"({surface_name(lines.wrap)})")
    return search


def _interrupted(stop: Interrupted, run_dir: Path, search: MaskSearch, mask, spec) -> Interrupted:
    """SIGINT / SIGTERM during the search or its outputs: the best point so far kept as a partial record unless the
    finished one is written; the Interrupted to report, saying where the search stopped and what it kept."""
    if search.record is not None:
        return Interrupted(stop.signum, f"the search finished; stopped while writing its outputs ({search.record} "
                                        f"is complete)")
    if search.finished:
        where = f"the search finished ({search.evaluations} evaluations) but its outputs were not written"
    else:
        where = f"the search stopped {search.position()}"
    path = _write_partial(run_dir / PARTIAL_RECORD, search, mask, spec, f"interrupted by {stop.name}: {where}")
    if path is None:
        return Interrupted(stop.signum, f"{where}; no evaluation had finished: no design to keep")
    return Interrupted(stop.signum, f"{where}; its best design so far: {path} (marked partial; to continue from it: "
                                    f"mask.init={path} search.init=mask)")


def _write_partial(path: Path, search: MaskSearch, mask, spec, reason: str) -> Path | None:
    """The main floor's best point so far (the feasible one, else the least violating) as a record marked partial,
    with the figures the search measured (not re-checked); None when no evaluation finished."""
    problem = search.sweeps[0].problem if search.sweeps else None
    x, feasible = problem.result_x() if problem is not None else (None, False)
    if x is None:
        return None
    ev = problem.best if feasible else problem.least
    mask.set_vector(torch.from_numpy(x))
    write_record(path, mask, spec, {
        "lsr_sampled": ev.lsr_sampled, "lsr_smooth": ev.lsr_smooth, "mtf_mean": ev.mtf_mean,
        "window_energy": ev.energy, "restorability": ev.restorability, "feasible": feasible, "partial": True,
        "stop_reason": reason})
    log.warning("%s: wrote the best point so far to %s (%s, LSR %.4g, mtf_mean %.4g; marked partial)", reason,
                path, "feasible" if feasible else "INFEASIBLE", ev.lsr_sampled, ev.mtf_mean)
    return path


def _add_limit(values: dict, arrays: dict, limit) -> None:
    """Window energy, the limit at this mtf_mean and energy, and the LSR's ratio to it, into ``values``."""
    values["window_energy"] = float(arrays["psf"].sum())
    values["lsr_limit"] = limit.lsr_limit(values["mtf_mean"], values["window_energy"])
    values["lsr_over_limit"] = values["lsr"] / values["lsr_limit"]


def _measure(monitor, limit, rest, mask) -> tuple[dict, dict]:
    values, arrays = monitor.measure(mask, refine=True)
    _add_limit(values, arrays, limit)
    values["restorability"] = rest.score(mask)
    return values, arrays


def _outputs(job: _Job, main) -> dict:
    """Measure and re-check the best design, sweep front, files and figures; returns metrics.json's content."""
    s, ms, system, mask, run_dir = job.s, job.ms, job.system, job.mask, job.run_dir
    monitor = MaskMonitor(system, None, ms.mtf_band, ms.lsr_p, ms.lsr_grids)
    front = _front(job, monitor)
    x, feasible = main.problem.result_x()
    if x is None:
        raise ConfigError("search", s.objective, "no evaluation finished with finite figures: nothing to report")
    mask.set_vector(torch.from_numpy(x))
    values, arrays = _measure(monitor, job.limit, job.rest, mask)
    _add_limit(job.base, job.base_arr, job.limit)
    if not feasible:
        log.error("NO FEASIBLE POINT in %d evaluations: the outputs describe the point closest to the constraints "
                  "(violation %.3g)", main.problem.evaluations, main.problem.least.violation,
                  extra={"smoke_expected": True})
    check, sampling = _recheck(job, mask)
    quantized = quantized_figures(mask, monitor, job.rest, (2, 4, 8, 16))
    figures = {k: values[k] for k in ("lsr", "lsr_smooth", "lsr_sampled", "mtf_mean", "window_energy", "lsr_limit",
                                      "lsr_over_limit", "restorability")}
    write_record(run_dir / "best_mask.json", mask, system.spec, {**figures, "feasible": feasible,
                                                                "check_agree": check["agree"] if check else None,
                                                                "phase_resolved": sampling["phase_resolved"]})
    job.search.record = run_dir / "best_mask.json"
    (run_dir / PARTIAL_RECORD).unlink(missing_ok=True)  # an earlier interrupted run's: this search finished
    _write_evaluations(run_dir / "evaluations.csv", job.search.sweeps, mask)
    metrics = {**figures, "mtf_min": values["mtf_min"], "bsr": values["bsr"], "feasible": feasible,
               "min_violation": 0.0 if feasible else main.problem.least.violation, **_record(job, main, values),
               "check": check, **sampling, "quantized": quantized, "pareto": front}
    if job.lines is not None:
        _line_metrics(job, metrics)
    io.write_json(run_dir / "metrics.json", metrics)
    _figures(run_dir, system, mask, (values, arrays), (job.base, job.base_arr), job.limit, ms, monitor.radial,
             job.search, front)
    _log_best(job, main, values, check, feasible, metrics["evals_per_second"])
    return metrics


def _front(job: _Job, monitor) -> list[dict]:
    """The best point of every floor of the sweep, measured: the front of pareto.png and metrics.json."""
    front = []
    for sw in job.search.sweeps:
        x, feasible = sw.problem.result_x()
        if x is None:
            continue
        job.mask.set_vector(torch.from_numpy(x))
        v, _ = _measure(monitor, job.limit, job.rest, job.mask)
        front.append({"factor": sw.factor, "mtf_floor": sw.limits.mtf, "feasible": feasible, "evaluations":
                      sw.problem.evaluations, "seconds": sw.seconds, **{k: v[k] for k in (
                          "lsr", "lsr_smooth", "mtf_mean", "bsr", "window_energy", "lsr_limit", "lsr_over_limit",
                          "restorability")}})
    return front


def _recheck(job: _Job, mask) -> tuple[dict | None, dict]:
    """The best design re-checked on a finer grid and a whole-PSF window (search.check), and its phase sampling:
    (the check or None, the sampling report)."""
    ms, spec = job.ms, job.system.spec
    check = verify_design(mask.freeze(), spec, ms.mtf_band, ms.recheck_tolerance) if job.s.check else None
    if check is not None and not check["agree"]:
        log.warning("the best design does NOT survive the re-check: its LSR / mtf_mean on a pupil grid twice as "
                    "fine and a window twice as wide differ by up to %.1f%% (tolerance %.0f%%): part of its gain is "
                    "the simulation's, not the optics' (metrics.json: check)", 100 * check["max_deviation"],
                    100 * ms.recheck_tolerance, extra={"smoke_expected": True})
    sampling = report_sampling(sampling_of(check["design"], check["fine"]), log, "the best design") if check \
        else sampling_report(mask.freeze(), spec, ms.mtf_band, log, "the best design")
    return check, sampling


def _record(job: _Job, main, values: dict) -> dict:
    """metrics.json's description of the design, the published baseline, the search and the optics."""
    s, ms, mask, base, search, spec = job.s, job.ms, job.mask, job.base, job.search, job.system.spec
    return {
        "mask_kind": mask.kind, "parameters": mask.vector_size, **mask.summary(),
        **{f"{k}_published": base[k] for k in ("lsr", "lsr_smooth", "mtf_mean", "mtf_min", "bsr", "window_energy",
                                              "lsr_limit", "lsr_over_limit", "restorability")},
        "lsr_vs_published": values["lsr"] / base["lsr"], "mtf_mean_uncoded": job.limit.uncoded_mtf_mean,
        "limits": {k: getattr(main.limits, k) for k in main.limits.active}, "objective": s.objective,
        "starts": main.starts, "evaluations": main.problem.evaluations, "evaluations_total": search.evaluations,
        "seconds": main.seconds, "evals_per_second": main.problem.evaluations / max(main.seconds, 1e-12),
        "algorithm": search.algorithm, "lsr_p_schedule": list(search.schedule), "n_starts": len(main.starts),
        "max_evals": search.max_evals, "seed": s.seed, "lsr_p": ms.lsr_p, "mtf_band_low": ms.mtf_band[0],
        "mtf_band_high": ms.mtf_band[1], "pupil_n": spec.grid_n, "pupil_pitch_m": spec.pupil_pitch_m,
        "focal_n": spec.focal_n, "focal_pitch_m": spec.focal_pitch_m, "propagator": job.system.method,
        "precision": s.precision, "device": str(job.device), "threads": torch.get_num_threads()}


def _line_metrics(job: _Job, metrics: dict) -> None:
    """The best and the published mask at every laser line, into ``metrics`` (laser_lines, lsr_worst_line*)."""
    mask = job.mask
    metrics["lsr_over"] = job.s.lsr_over
    metrics["laser_lines"] = summary = lines_summary(job.lines, {"best": mask.phase().detach(), "published":
                                                                 job.published.phase().detach()}, mask.plate_cell_m)
    for name, label in (("best", f"best {mask.kind}"), ("published", "published mask")):
        log_lines(summary, name, label)
        metrics[f"lsr_worst_line{'' if name == 'best' else '_published'}"] = summary[name]["lsr_worst"]


def _log_best(job: _Job, main, values: dict, check: dict | None, feasible: bool, rate: float) -> None:
    """The search's one closing line: the best design against the published one, the re-check, the cost."""
    base = job.base
    log.info("best %s: LSR %.4g (published %.4g, %.2fx the limit %.4g), mtf_mean %.4g, window energy %.4f, "
             "restorability %.2f dB (published %.2f)%s; %d evaluations in %.0f s (%.2f/s); wrote %s",
             "design" if feasible else "INFEASIBLE point", values["lsr"], base["lsr"], values["lsr_over_limit"],
             values["lsr_limit"], values["mtf_mean"], values["window_energy"], values["restorability"],
             base["restorability"], "" if check is None else f"; re-check {'agrees' if check['agree'] else 'FAILS'} "
             f"(max deviation {100 * check['max_deviation']:.2f}%)", main.problem.evaluations, main.seconds,
             rate, job.run_dir, extra={"smoke_expected": not feasible or (check is not None and not check["agree"])})


def _write_evaluations(path: Path, sweeps, mask) -> None:
    names = mask.vector_names() if mask.vector_size <= 64 else None
    buf = _stringio.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["floor_factor", "mtf_floor", "start", "lsr_p", "lsr_sampled", "lsr_smooth", "mtf_mean",
                "window_energy", "restorability", "feasible", *(names or [])])
    for sw in sweeps:
        for ev in sw.problem.records:
            w.writerow([sw.factor, sw.limits.mtf, ev.label, ev.p, ev.lsr_sampled, ev.lsr_smooth, ev.mtf_mean,
                        ev.energy, ev.restorability, int(ev.feasible),
                        *(ev.x.tolist() if names and ev.x is not None else [])])
    io.atomic_write_bytes(path, lambda f: f.write(buf.getvalue().encode()))


def _figures(run_dir: Path, system, mask, best, baseline, limit, ms, radial, search, front) -> None:
    import math

    from codesign.io.tensorboard import log_mask

    (values, arrays), (base, base_arr) = best, baseline
    spec = system.spec
    ap = system.grid.aperture.cpu().numpy()
    np_ = lambda t: t.detach().cpu().numpy()  # noqa: E731
    with torch.no_grad():
        psf0 = system.uncoded_psf()
        rad0 = radial(metrics.mtf(psf0))
    for name, v, arr, who in (("", values, arrays, f"best {mask.kind}"), ("published_", base, base_arr, "published")):
        io.save_figure(run_dir / f"{name}phase.png", plots.phase_figure(np_(arr["phase"]), ap, spec.pupil_pitch_m,
                                                                       f"{who} mask: pupil phase"))
        io.save_figure(run_dir / f"{name}psf_log.png", plots.psf_figure(
            np_(arr["psf"]), np_(psf0), spec.focal_pitch_m, f"{who} mask: LSR = {v['lsr']:.3g}, "
            f"mtf_mean = {v['mtf_mean']:.3g}"))
    freqs = np_(radial.freqs)
    io.save_figure(run_dir / "mtf.png", plots.mtf_figure(
        freqs, {"best mask": np_(arrays["mtf_radial"]), "published mask": np_(base_arr["mtf_radial"]),
                "uncoded": np_(rad0), "analytic circular pupil": circular_mtf(torch.from_numpy(freqs)).numpy()},
        ms.mtf_band, f"MTF: best mean {values['mtf_mean']:.3g}, published {base['mtf_mean']:.3g}"))
    if search.writer is not None:  # the best design's figures, phase, PSF and MTF; the published mask's figures
        step = search.evaluations
        finite = lambda d: {k: float(v) for k, v in d.items()  # noqa: E731
                            if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)}
        log_mask(search.writer, step, mask, finite(values), arrays, reference=(base, base_arr), aperture=ap,
                 uncoded_peak=system.uncoded_peak, freqs=np_(radial.freqs), band=ms.mtf_band, prefix="best")
        for k, v in finite(base).items():
            search.writer.add_scalar(f"published/{k}", v, step)
        search.writer.flush()
    io.save_figure(run_dir / "pareto.png", evaluations_figure(search.sweeps, front, base, limit, "sampled",
                                                              best=values, best_label=f"searched {mask.kind}"))



