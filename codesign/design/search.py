"""The mask search: starts, the floor sweep and the progress report around DesignProblem and the optimizers.

``MaskSearch`` runs every start of the main floor, then the Pareto sweep (other floor factors, warm-started from
the main floor's best), printing a progress line every ``log_every`` evaluations with the best feasible point and
an ETA over the whole run's evaluation budget. The outputs (records, figures, checks) are the task's.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from codesign.design.optimize import run_start
from codesign.design.problem import DesignProblem, Limits

log = logging.getLogger("codesign.mask_search")


@dataclass
class Sweep:
    """One floor of the search: its factor, its limits, its DesignProblem and per-start records."""

    factor: float
    limits: Limits
    problem: DesignProblem
    starts: list = field(default_factory=list)
    seconds: float = 0.0


class MaskSearch:
    """Searches ``mask`` (its parameter vector) on ``system``.

    Args:
        spec: SearchSpec; limits: the main floor's Limits; make_problem: Limits -> DesignProblem; starts: the
        labelled start vectors [(label, kind, x0)] of the main floor; random_start: rng -> vector (sweep starts);
        bounds: (lower, upper) numpy vectors; schedule: the p continuation.
    """

    def __init__(self, spec, n: int, limits: Limits, make_problem, starts, random_start, bounds, schedule,
                 writer=None):
        self.s, self.n, self.limits, self.make_problem = spec, n, limits, make_problem
        self.start_points, self.random_start, self.bounds = starts, random_start, bounds
        self.schedule, self.writer = tuple(schedule), writer
        self.algorithm = spec.resolved_algorithm(n)
        self.max_evals = spec.resolved_max_evals(n)
        self.sweep_evals = spec.pareto_max_evals if spec.pareto_max_evals is not None else max(self.max_evals // 2, 1)
        factors = [f for f in (spec.pareto_factors or ()) if not math.isclose(f, spec.mtf_floor_factor, rel_tol=1e-9)]
        polish = spec.polish_max_evals if self.algorithm.startswith("G") else 0
        self.budget = len(starts) * (self.max_evals + polish) + len(factors) * spec.pareto_starts * (
            self.sweep_evals + polish)
        self.factors = factors
        self.sweeps: list[Sweep] = []
        self.t0 = time.perf_counter()
        self.done = 0
        self.at = ""  # the start running now ("start 0 of the search"): where an interrupt stopped the search
        self.finished = False  # every start of every floor ran to its end
        self.record = None  # the finished record's path, once the task has written it

    # ---- progress ---------------------------------------------------------------------------------------------
    def _on_eval(self, sweep_tag: str):
        def on_eval(problem: DesignProblem, ev) -> None:
            self.done += 1
            k = problem.evaluations
            if self.writer is not None:
                self._log_eval(sweep_tag, problem, ev, k)
            if self.done % self.s.log_every == 0:
                elapsed = time.perf_counter() - self.t0
                rate = self.done / max(elapsed, 1e-9)
                best = problem.best
                text = (f"LSR {best.lsr_sampled:.4g} (mtf_mean {best.mtf_mean:.4g}, E {best.energy:.4f})"
                        if best else f"none yet (violation {problem.least.violation:.3g})" if problem.least else "none")
                log.info("%s start %s, p %g: eval %d: LSR %.4g mtf_mean %.4g E %.4f; best feasible %s; %.2f evals/s, "
                         "ETA %.0f s", sweep_tag, problem.label, ev.p, k, ev.lsr_sampled, ev.mtf_mean, ev.energy, text,
                         rate, max(self.budget - self.done, 0) / rate)
        return on_eval

    def _log_eval(self, tag: str, problem: DesignProblem, ev, k: int) -> None:
        """One evaluation's progress in TensorBoard at step ``k`` (the floor's evaluation count): the objective, each
        constraint's value (<= 0: met), the violation, LSR (sampled and smooth), mtf_mean, window energy, the
        restorability when measured, the p of the continuation and the best feasible point's figures so far."""
        w = self.writer
        figures = {"objective": ev.objective, "lsr_sampled": ev.lsr_sampled, "lsr_smooth": ev.lsr_smooth,
                   "mtf_mean": ev.mtf_mean, "window_energy": ev.energy, "violation": ev.violation, "lsr_p": ev.p,
                   "restorability": ev.restorability,
                   **{f"constraint/{name}": v for name, v in ev.constraints.items()}}
        best = problem.best
        if best is not None:
            figures.update({"best/lsr_sampled": best.lsr_sampled, "best/mtf_mean": best.mtf_mean,
                            "best/objective": best.objective})
        for name, v in figures.items():
            if v is not None and math.isfinite(float(v)):
                w.add_scalar(f"{tag}/{name}", float(v), k)
        if self.done % self.s.log_every == 0:
            w.flush()

    # ---- the run ----------------------------------------------------------------------------------------------
    def _run_sweep(self, factor: float, limits: Limits, starts, max_evals: int, tag: str) -> Sweep:
        problem = self.make_problem(limits)
        problem.on_eval = self._on_eval(tag)
        sweep = Sweep(factor, limits, problem)
        self.sweeps.append(sweep)  # now, not when done: an interrupted search keeps its best point so far
        t0 = time.perf_counter()
        for label, kind, x0 in starts:
            self.at = f"start {label} of {'the search' if tag == 'search' else f'the sweep at floor x{factor:g}'}"
            res = {"init": kind, **run_start(problem, label, np.asarray(x0, dtype=np.float64), self.bounds,
                                             self.algorithm, self.s.local_algorithm, self.schedule, max_evals,
                                             self.s.polish_max_evals, self.s.xtol_rel, self.s.ftol_rel)}
            sweep.starts.append(res)
            log.info("%s: start %s (%s) after %d evaluations: %s", tag, label, kind, res["evaluations"],
                     f"LSR {res['lsr']:.4g}, mtf_mean {res['mtf_mean']:.4g}" if res["feasible"]
                     else f"no feasible point (violation {res['min_violation']:.3g})")
        sweep.seconds = time.perf_counter() - t0
        self.at = ""
        return sweep

    def run(self) -> Sweep:
        """Every start of the main floor, then the sweep; returns the main floor's Sweep."""
        main = self._run_sweep(self.s.mtf_floor_factor, self.limits, self.start_points, self.max_evals, "search")
        rng = np.random.default_rng(self.s.seed + 1)
        for f in self.factors:
            warm, _ = main.problem.result_x()
            pts = [("0", "warm", warm)] + [(str(i), "random", self.random_start(rng).numpy())
                                            for i in range(1, self.s.pareto_starts)]
            limits = replace(self.limits, mtf=None if self.limits.mtf is None
                             else self.limits.mtf / self.s.mtf_floor_factor * f)
            self._run_sweep(f, limits, pts, self.sweep_evals, f"pareto_x{f:g}")
        self.finished = True
        return main

    @property
    def evaluations(self) -> int:
        """Evaluations made so far, over every floor of the sweep."""
        return sum(sw.problem.evaluations for sw in self.sweeps)

    def position(self) -> str:
        """Where the search is: "in start 0 of the search after 57 of 816 evaluations"."""
        where = f"in {self.at} " if self.at else ""
        return f"{where}after {self.done} of {self.budget} evaluations"


def start_points(init_x: torch.Tensor | None, init: str, count: int, random_start, seed: int) -> list:
    """(label, kind, x0) of ``count`` starts: the configured ``init`` at init_x (None: random), then random starts
    from ``seed`` (the same for every floor, so floors are comparable)."""
    rng = np.random.default_rng(seed)
    pts = [(init, init_x.numpy())] if init_x is not None else []
    while len(pts) < count:
        pts.append(("random", random_start(rng).numpy()))
    return [(str(i), kind, x) for i, (kind, x) in enumerate(pts[:count])]
