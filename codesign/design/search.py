"""Mask-only search with nlopt: minimize the LSR of a half-ring mask under an MTF floor.

Variables x = [r_1..r_N, theta_1..theta_N] (r in units of lambda f / W_a, theta in rad), boxed by the search
bounds. Objective f(x) = log(lsr_smooth): the LSR spans decades, and the log keeps the function values and the
gradient steps of the optimizers on a sane scale. Constraint c(x) = log(floor) - log(mtf_mean) <= 0: the relative
form is as well scaled for a floor of 0.04 (the published mask) as for one of 0.4. Optional second constraint
e(x) = log(energy_floor) - log(E_w) <= 0, E_w = the PSF energy inside the optics window: without it a search
learns to push the PSF's peak and energy beyond the window, where neither the LSR nor the MTF sees them
(docs/codesign.md, "the window artefact").

nlopt asks for the objective and the constraint at the same x, one call after the other; ``MaskObjective`` computes
both in one forward pass (and, for gradient-based algorithms, two backward passes through the same graph) and
answers the second call from a one-entry cache. It records every evaluation and keeps the best feasible point
itself, because nlopt may end at an infeasible point or stop with an exception.
"""
from __future__ import annotations

import logging
import math
import re
import time
from dataclasses import dataclass
from typing import Callable

import nlopt
import numpy as np
import torch

from codesign.errors import ConfigError
from codesign.optics import metrics

log = logging.getLogger("codesign.mask_search")

# nlopt supports nonlinear inequality constraints only in these algorithms (nlopt documentation, "Nonlinear
# constraints"); every other algorithm would reject add_inequality_constraint with invalid_argument.
CONSTRAINED = ("LD_MMA", "LD_CCSAQ", "LD_SLSQP", "LN_COBYLA", "GN_ISRES", "GN_AGS", "GN_ORIG_DIRECT",
               "GN_ORIG_DIRECT_L")
LOCAL = tuple(a for a in CONSTRAINED if a.startswith("L"))
_NLOPT_NAMES = frozenset(a for a in dir(nlopt) if re.match(r"^(G[ND]?|L[ND])_|^(LD_|LN_)?AUGLAG", a))
RESULTS = {nlopt.SUCCESS: "SUCCESS", nlopt.STOPVAL_REACHED: "STOPVAL_REACHED", nlopt.FTOL_REACHED: "FTOL_REACHED",
           nlopt.XTOL_REACHED: "XTOL_REACHED", nlopt.MAXEVAL_REACHED: "MAXEVAL_REACHED",
           nlopt.MAXTIME_REACHED: "MAXTIME_REACHED", nlopt.FAILURE: "FAILURE", nlopt.INVALID_ARGS: "INVALID_ARGS",
           nlopt.OUT_OF_MEMORY: "OUT_OF_MEMORY", nlopt.ROUNDOFF_LIMITED: "ROUNDOFF_LIMITED",
           nlopt.FORCED_STOP: "FORCED_STOP"}
# What nlopt's optimize() raises for its own failure codes (besides RoundoffLimited / ForcedStop).
_NLOPT_ERRORS = (nlopt.RoundoffLimited, nlopt.ForcedStop, nlopt.invalid_argument, RuntimeError, ValueError,
                 MemoryError)


def check_algorithm(key: str, name, allowed: tuple[str, ...]) -> int:
    """nlopt's code of algorithm ``name``; ConfigError if nlopt has none of that name or it is not in ``allowed``."""
    listed = ", ".join(allowed)
    if not isinstance(name, str) or name not in _NLOPT_NAMES:
        raise ConfigError(key, name, f"not an nlopt algorithm; allowed: {listed}")
    if name not in allowed:
        why = ("cannot handle the inequality constraint mtf_mean >= floor" if name not in CONSTRAINED
               else "is a global algorithm; the polish needs a local one")
        raise ConfigError(key, name, f"nlopt's {name} {why}; allowed: {listed}")
    return getattr(nlopt, name)


@dataclass
class Evaluation:
    """One evaluated point: x (float64), lsr_smooth, mtf_mean, feasible; f, c and their gradients (or None);
    energy: PSF energy in the window, e / grad_e its constraint (0 and None without an energy floor), energy_ok."""
    x: np.ndarray
    lsr_smooth: float
    mtf_mean: float
    feasible: bool
    f: float
    c: float
    grad_f: np.ndarray | None = None
    grad_c: np.ndarray | None = None
    energy: float = 1.0
    e: float = 0.0
    grad_e: np.ndarray | None = None
    energy_ok: bool = True


class MaskObjective:
    """nlopt callbacks for a half-ring mask on an optical system, with the evaluation log and the best points.

    Args:
        system: OpticalSystem; mask: HalfRingMask (its r, theta are overwritten by every evaluation);
        radial: RadialMTF of the system; band: MTF band (normalized frequency); p: smooth-LSR exponent;
        floor: the MTF floor (band mean, dimensionless); on_eval: called with (self, Evaluation) after each new
        point (progress lines, TensorBoard).
    """

    def __init__(self, system, mask, radial, band: tuple[float, float], p: float, floor: float,
                 on_eval: Callable | None = None, energy_floor: float | None = None):
        self.system, self.mask, self.radial, self.band, self.p = system, mask, radial, tuple(band), p
        self.floor, self.on_eval = float(floor), on_eval
        self.energy_floor = None if energy_floor is None else float(energy_floor)
        self.n = mask.r.numel()
        self.records: list[tuple[str, int, Evaluation]] = []  # (start label, eval index in start, evaluation)
        self.best: Evaluation | None = None         # lowest lsr_smooth among feasible points, all starts
        self.least_violating: Evaluation | None = None  # smallest floor - mtf_mean, all starts
        self.start_best: Evaluation | None = None
        self.start_least: Evaluation | None = None
        self.label, self.start_evals, self.error = "0", 0, None
        self._last: Evaluation | None = None

    # ---- evaluation -----------------------------------------------------------------------------------------
    def _forward(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        psf = self.system.psf(self.mask.phase())
        lsr = metrics.lsr_smooth(psf, self.system.uncoded_peak, self.p)
        mean, _ = self.radial.summary(self.radial(metrics.mtf(psf)), self.band)
        return lsr, mean, psf.sum()

    def compute(self, x: np.ndarray, need_grad: bool) -> Evaluation:
        """f, c (and their gradients w.r.t. x when ``need_grad``) at x; no bookkeeping."""
        x = np.array(x, dtype=np.float64)  # nlopt's x is a read-only view; torch wants its own memory
        with torch.no_grad():
            self.mask.r.copy_(torch.from_numpy(x[:self.n]))
            self.mask.theta.copy_(torch.from_numpy(x[self.n:]))
        params = [self.mask.r, self.mask.theta]
        gf = gc = ge = None
        with torch.set_grad_enabled(need_grad):
            lsr, mean, energy = self._forward()
            f = torch.log(lsr)
            c = math.log(self.floor) - torch.log(mean)
            e = None if self.energy_floor is None else math.log(self.energy_floor) - torch.log(energy)
            if need_grad:
                # One backward pass per function through one forward: every gradient is needed at every point and
                # the forward (Bessel profiles, pupil field, MFT) is the larger half of the cost.
                gf = torch.cat(torch.autograd.grad(f, params, retain_graph=True)).double().cpu().numpy()
                gc = torch.cat(torch.autograd.grad(c, params, retain_graph=e is not None)).double().cpu().numpy()
                if e is not None:
                    ge = torch.cat(torch.autograd.grad(e, params)).double().cpu().numpy()
        lsr_v, mean_v, energy_v = float(lsr.detach()), float(mean.detach()), float(energy.detach())
        energy_ok = self.energy_floor is None or energy_v >= self.energy_floor
        return Evaluation(x, lsr_v, mean_v, mean_v >= self.floor and energy_ok, float(f.detach()),
                          float(c.detach()), gf, gc, energy_v, 0.0 if e is None else float(e.detach()), ge,
                          energy_ok)

    def _get(self, x: np.ndarray, need_grad: bool) -> Evaluation:
        last = self._last
        if last is not None and np.array_equal(last.x, x) and (last.grad_f is not None or not need_grad):
            return last
        try:
            ev = self.compute(x, need_grad)
            if not (math.isfinite(ev.f) and math.isfinite(ev.c) and math.isfinite(ev.e)):
                raise nlopt.ForcedStop(f"non-finite objective or constraint at x = {x.tolist()}: lsr_smooth "
                                       f"{ev.lsr_smooth}, mtf_mean {ev.mtf_mean}")
            if last is None or not np.array_equal(last.x, x):  # a gradient re-request is not a new point
                self._record(ev)
        except nlopt.ForcedStop:
            raise
        except Exception as err:  # noqa: BLE001 - kept and re-raised after optimize(): a bug, not an nlopt outcome
            # nlopt turns an exception in a callback into a forced stop and re-raises it from optimize(), where
            # a RuntimeError from torch would look like nlopt's own failure; keep it to re-raise as what it is.
            self.error = err
            raise nlopt.ForcedStop(f"evaluation failed: {err}") from err
        self._last = ev
        return ev

    def _record(self, ev: Evaluation) -> None:
        self.records.append((self.label, self.start_evals, ev))
        self.start_evals += 1
        if ev.feasible:
            if self.best is None or ev.lsr_smooth < self.best.lsr_smooth:
                self.best = ev
            if self.start_best is None or ev.lsr_smooth < self.start_best.lsr_smooth:
                self.start_best = ev
        viol = self.floor - ev.mtf_mean
        if self.least_violating is None or viol < self.floor - self.least_violating.mtf_mean:
            self.least_violating = ev
        if self.start_least is None or viol < self.floor - self.start_least.mtf_mean:
            self.start_least = ev
        if self.on_eval is not None:
            self.on_eval(self, ev)

    # ---- nlopt callbacks ------------------------------------------------------------------------------------
    def objective(self, x: np.ndarray, grad: np.ndarray) -> float:
        ev = self._get(x, grad.size > 0)
        if grad.size > 0:
            grad[:] = ev.grad_f
        return ev.f

    def constraint(self, x: np.ndarray, grad: np.ndarray) -> float:
        ev = self._get(x, grad.size > 0)
        if grad.size > 0:
            grad[:] = ev.grad_c
        return ev.c

    def energy_constraint(self, x: np.ndarray, grad: np.ndarray) -> float:
        ev = self._get(x, grad.size > 0)
        if grad.size > 0:
            grad[:] = ev.grad_e
        return ev.e

    def begin_start(self, label: str) -> None:
        self.label, self.start_evals, self.start_best, self.start_least = label, 0, None, None
        self._last = None


def _optimize(obj: MaskObjective, algorithm: str, x0: np.ndarray, lower: np.ndarray, upper: np.ndarray,
              max_evals: int, xtol_rel: float, ftol_rel: float) -> dict:
    """One nlopt run from x0; returns its outcome (result code and name, exception text, evaluations)."""
    opt = nlopt.opt(getattr(nlopt, algorithm), x0.size)
    opt.set_lower_bounds(lower)
    opt.set_upper_bounds(upper)
    opt.set_min_objective(obj.objective)
    opt.add_inequality_constraint(obj.constraint, 0.0)
    if obj.energy_floor is not None:
        opt.add_inequality_constraint(obj.energy_constraint, 0.0)
    opt.set_maxeval(int(max_evals))
    opt.set_xtol_rel(xtol_rel)
    opt.set_ftol_rel(ftol_rel)
    before, exc = obj.start_evals, None
    try:
        opt.optimize(np.clip(x0, lower, upper))
    except _NLOPT_ERRORS as err:
        if obj.error is not None:  # our own evaluation failed: a bug to show, not an optimizer outcome
            raise obj.error
        exc = f"{type(err).__name__}: {err}".rstrip(": ")
    code = opt.last_optimize_result()
    out = {"algorithm": algorithm, "result_code": int(code), "result": RESULTS.get(code, str(code)),
           "exception": exc, "evaluations": obj.start_evals - before}
    if exc is not None or code < 0:
        log.warning("start %s: %s ended with %s%s", obj.label, algorithm, out["result"],
                    f" ({exc})" if exc else "")
    return out


def run_start(obj: MaskObjective, label: str, x0: np.ndarray, lower: np.ndarray, upper: np.ndarray,
              algorithm: str, local_algorithm: str | None, max_evals: int, polish_evals: int,
              xtol_rel: float, ftol_rel: float) -> dict:
    """One start: ``algorithm`` from x0, then (global algorithms only) a local polish from the start's best
    feasible point (or its least violating one). Returns the per-start record written to metrics.json."""
    obj.begin_start(label)
    t0 = time.perf_counter()
    out = {"start": label, **_optimize(obj, algorithm, x0, lower, upper, max_evals, xtol_rel, ftol_rel)}
    if algorithm.startswith("G") and local_algorithm and polish_evals > 0 and obj.start_least is not None:
        seed = obj.start_best or obj.start_least
        out["polish"] = _optimize(obj, local_algorithm, seed.x, lower, upper, polish_evals, xtol_rel, ftol_rel)
    best, least = obj.start_best, obj.start_least
    out.update({"evaluations": obj.start_evals, "seconds": time.perf_counter() - t0, "feasible": best is not None,
                "lsr_smooth": best.lsr_smooth if best else None, "mtf_mean": best.mtf_mean if best else None,
                "min_violation": max(obj.floor - least.mtf_mean, 0.0) if least else None,
                "x": (best or least).x.tolist() if least else None})
    return out


def start_points(init: str, init_x: np.ndarray | None, seed: int, lower: np.ndarray, upper: np.ndarray,
                 count: int, warm: np.ndarray | None = None) -> list[tuple[str, str, np.ndarray]]:
    """(label, kind, x0) of ``count`` starts: the warm start (Pareto sweep), the configured ``init`` at init_x, then
    uniform random points in the box from ``seed`` (the same points for every floor, so floors are comparable)."""
    rng = np.random.default_rng(seed)
    pts = ([("warm", warm)] if warm is not None else []) + ([(init, init_x)] if init_x is not None else [])
    while len(pts) < count:
        pts.append(("random", lower + (upper - lower) * rng.random(lower.size)))
    return [(str(i), kind, x) for i, (kind, x) in enumerate(pts[:count])]


def best_point(sweeps: list[dict], floor: float) -> tuple[Evaluation, bool, float]:
    """(evaluation, feasible, factor of the sweep that found it); ``sweeps``: dicts with "factor" and "objective"
    (a MaskObjective). The point is the lowest lsr_smooth with mtf_mean >= floor among
    the evaluations of every sweep so far (a point found under a higher floor also meets a lower one, so the front
    stays monotone), else the point closest to the floor (highest mtf_mean)."""
    pts = [(ev, sw["factor"]) for sw in sweeps for _, _, ev in sw["objective"].records]
    ok = [p for p in pts if p[0].mtf_mean >= floor and p[0].energy_ok]
    if ok:
        ev, factor = min(ok, key=lambda p: p[0].lsr_smooth)
        return ev, True, factor
    ev, factor = max(pts, key=lambda p: p[0].mtf_mean)
    return ev, False, factor
