"""Searches over a DesignProblem's parameter vector: nlopt's constrained algorithms, and AL_LBFGS, an augmented
Lagrangian whose inner problems nlopt's LD_LBFGS solves, both under a continuation on the smooth-LSR exponent p.

AL_LBFGS (the high-dimensional default): for each p of the schedule, a few outer iterations, each minimizing
    L(x) = f_p(x) + sum_i [relu(mu_i + rho c_i(x))^2 - mu_i^2] / (2 rho)
with LD_LBFGS (one forward and one backward pass per evaluation: the gradient of L is that of
f + sum_i relu(mu_i + rho c_i) c_i), then mu_i <- relu(mu_i + rho c_i), and rho x4 when the worst violation did not
shrink 4x. A smooth LSR at small p sees the whole PSF, at large p only its highest peaks: starting at p = 16 and
ending near the true maximum lets the early stages shape the PSF and the late ones flatten its top. What it reaches
on every family, and in what time, is measured in docs/codesign.md Sec. 5 (benchmarks: design).
"""
from __future__ import annotations

import faulthandler
import io
import logging
import math
import re
import signal
import time

import nlopt
import numpy as np

from codesign.errors import ConfigError
from codesign.signals import Interrupted, stop_requests

log = logging.getLogger("codesign.mask_search")

# nlopt supports nonlinear inequality constraints only in these algorithms (nlopt documentation, "Nonlinear
# constraints"); every other algorithm would reject add_inequality_constraint with invalid_argument.
CONSTRAINED = ("LD_MMA", "LD_CCSAQ", "LD_SLSQP", "LN_COBYLA", "GN_ISRES", "GN_AGS", "GN_ORIG_DIRECT",
               "GN_ORIG_DIRECT_L")
LOCAL = tuple(a for a in CONSTRAINED if a.startswith("L"))
OWN = ("AL_LBFGS",)  # codesign's augmented Lagrangian on nlopt's LD_LBFGS
ALGORITHMS = CONSTRAINED + OWN
# the most parameters an nlopt algorithm runs on (nlopt 2.11, measured on a quadratic with one constraint): above,
# it refuses (AGS), crashes the process without a word (the original DIRECT, ISRES's population out of memory) or
# takes hours and gigabytes (SLSQP). A family's parameters: half rings 10, spiral 3, Zernike 36, spline 11025
# (debug=smoke) to 42025, pixel 31109 to 125081.
SIZE_LIMITS = {
    "GN_AGS": (10, "nlopt's AGS takes at most 10 dimensions (invalid_argument above)"),
    "GN_ORIG_DIRECT": (33, "nlopt's original DIRECT crashes the process (a segmentation fault) from 34 parameters"),
    "GN_ORIG_DIRECT_L": (33, "nlopt's original DIRECT crashes the process (a segmentation fault) from 34 "
                             "parameters"),
    "GN_ISRES": (1000, "ISRES holds a population of 20 (n + 1) points of n parameters: 11025 parameters need ~19 GB "
                       "(the process crashes), and above ~1000 one generation outlasts any evaluation budget"),
    "LD_SLSQP": (500, "SLSQP's dense quasi-Newton matrix takes n^2 memory and n^3 time per step (500 parameters: 21 s "
                      "of its own per 100 evaluations; 11025: over 4 GB)"),
}
_NLOPT_NAMES = frozenset(a for a in dir(nlopt) if re.match(r"^(G[ND]?|L[ND])_|^(LD_|LN_)?AUGLAG", a))
RESULTS = {nlopt.SUCCESS: "SUCCESS", nlopt.STOPVAL_REACHED: "STOPVAL_REACHED", nlopt.FTOL_REACHED: "FTOL_REACHED",
           nlopt.XTOL_REACHED: "XTOL_REACHED", nlopt.MAXEVAL_REACHED: "MAXEVAL_REACHED",
           nlopt.MAXTIME_REACHED: "MAXTIME_REACHED", nlopt.FAILURE: "FAILURE", nlopt.INVALID_ARGS: "INVALID_ARGS",
           nlopt.OUT_OF_MEMORY: "OUT_OF_MEMORY", nlopt.ROUNDOFF_LIMITED: "ROUNDOFF_LIMITED",
           nlopt.FORCED_STOP: "FORCED_STOP"}
INTERRUPTED = "INTERRUPTED"  # an outcome's result when SIGINT / SIGTERM stopped the run (nlopt: a forced stop)
# what the search does on SIGINT / SIGTERM (codesign/signals.py: stop_requests)
_ON_SIGNAL = ("stopping the search at the next evaluation (the best design so far is kept, marked partial; again "
              "to stop at once)")
# What nlopt's optimize() raises for its own failure codes (besides RoundoffLimited / ForcedStop): nlopt >= 2.8 has
# its own exception classes (nlopt.runtime_error is not a RuntimeError), older versions raise the builtin ones.
_NLOPT_FAILURES = (getattr(nlopt, "exception", RuntimeError), RuntimeError, ValueError, MemoryError)
_NLOPT_ERRORS = (nlopt.RoundoffLimited, nlopt.ForcedStop, nlopt.invalid_argument) + _NLOPT_FAILURES


def check_algorithm(key: str, name, allowed: tuple[str, ...]) -> str:
    """``name`` if it is in ``allowed``; a ConfigError saying why not otherwise."""
    listed = ", ".join(allowed)
    if not isinstance(name, str) or (name not in _NLOPT_NAMES and name not in OWN):
        raise ConfigError(key, name, f"not an nlopt algorithm nor {', '.join(OWN)}; allowed: {listed}")
    if name not in allowed:
        why = ("cannot handle the inequality constraints" if name not in CONSTRAINED + OWN
               else "is a global algorithm; the polish needs a local one")
        raise ConfigError(key, name, f"nlopt's {name} {why}; allowed: {listed}")
    return name


def check_size(key: str, name: str, n: int, family: str, allowed: tuple[str, ...]) -> None:
    """ConfigError naming ``key`` when algorithm ``name`` cannot run a ``family`` mask of ``n`` parameters
    (SIZE_LIMITS), with the algorithms of ``allowed`` that can: refused before the search, not a crash in it."""
    limit, why = SIZE_LIMITS.get(name, (None, ""))
    if limit is not None and n > limit:
        fits = [a for a in allowed if SIZE_LIMITS.get(a, (n,))[0] >= n]
        raise ConfigError(key, name, f"cannot search a {family} mask of {n} parameters (at most {limit}: {why}); "
                          f"allowed for this mask: {', '.join(fits)}")


def _crash_report() -> None:
    """Python's fault handler on: a crash inside nlopt's C code (which SIZE_LIMITS keep the searches away from)
    then prints "Fatal Python error: Segmentation fault" and where the search was, not nothing."""
    if not faulthandler.is_enabled():
        try:
            faulthandler.enable()
        except (AttributeError, ValueError, io.UnsupportedOperation):  # a stderr without a file descriptor
            pass


def _outcome(algorithm: str, code, exc, evaluations: int) -> dict:
    out = {"algorithm": algorithm, "result_code": int(code), "result": RESULTS.get(code, str(code)),
           "exception": exc, "evaluations": evaluations}
    if exc is not None or code < 0:
        log.warning("%s ended with %s%s", algorithm, out["result"], f" ({exc})" if exc else "")
    return out


def _stoppable(callback, signals: list):
    """``callback`` (an nlopt objective or constraint) that first raises nlopt.ForcedStop once ``signals`` holds a
    signal: nlopt ends optimize() with it at an evaluation boundary. Raising the interrupt itself inside the callback
    is not an option: depending on where it lands nlopt reports it as its own failure (runtime_error) and the search
    went on."""
    def checked(x, grad):
        if signals:
            raise nlopt.ForcedStop(f"interrupted by {signal.Signals(signals[0]).name}")
        return callback(x, grad)
    return checked


def _interrupted(algorithm: str, signals: list, evaluations: int) -> Interrupted:
    """The Interrupted that ends the search after an nlopt run that ``signals`` stopped; its outcome is logged as
    what it is (an interrupt, not nlopt's FORCED_STOP or a failure)."""
    stop = Interrupted(signals[0])
    stop.outcome = {"algorithm": algorithm, "result_code": int(nlopt.FORCED_STOP), "result": INTERRUPTED,
                    "exception": None, "evaluations": evaluations, "signal": stop.name}
    log.warning("%s stopped: %s by %s after %d evaluation(s)", algorithm, INTERRUPTED, stop.name, evaluations)
    return stop


def run_nlopt(problem, algorithm: str, x0: np.ndarray, lower: np.ndarray, upper: np.ndarray, p: float,
              max_evals: int, xtol_rel: float, ftol_rel: float) -> tuple[np.ndarray, dict]:
    """One nlopt run with the objective and every constraint of ``problem``; returns (last x, outcome). SIGINT /
    SIGTERM: Interrupted (with ``outcome``) at the next evaluation."""
    cache: dict = {}
    error: list = []
    signals: list = []  # filled by stop_requests below; the callbacks read it

    def get(x, need):
        key = x.tobytes()
        if key in cache and (cache[key][1] is not None or not need):
            return cache[key]
        try:
            ev, grad = problem.evaluate(x, p, need)
        except nlopt.ForcedStop:  # a deliberate stop (e.g. from an on_eval callback): nlopt's outcome
            raise
        except Exception as err:  # noqa: BLE001 - re-raised after optimize() as what it is, not as nlopt's failure
            error.append(err)
            raise nlopt.ForcedStop(f"evaluation failed: {err}") from err
        if not all(math.isfinite(v) for v in (ev.objective, *ev.constraints.values())):
            raise nlopt.ForcedStop(f"non-finite objective or constraint: {ev}")
        cache.clear()
        cache[key] = (ev, grad)
        return ev, grad

    def objective(x, grad):
        ev, g = get(x, grad.size > 0)
        if grad.size > 0:
            grad[:] = g["objective"]
        return ev.objective

    def constraint(name):
        def c(x, grad):
            ev, g = get(x, grad.size > 0)
            if grad.size > 0:
                grad[:] = g[name]
            return ev.constraints[name]
        return c

    _crash_report()
    opt = nlopt.opt(getattr(nlopt, algorithm), x0.size)
    opt.set_lower_bounds(lower)
    opt.set_upper_bounds(upper)
    opt.set_min_objective(_stoppable(objective, signals))
    for name in problem.limits.active:
        opt.add_inequality_constraint(_stoppable(constraint(name), signals), 0.0)
    opt.set_maxeval(int(max_evals))
    opt.set_xtol_rel(xtol_rel)
    opt.set_ftol_rel(ftol_rel)
    before, exc, x = problem.evaluations, None, np.clip(x0, lower, upper)
    with stop_requests(_ON_SIGNAL, signals):
        try:
            x = opt.optimize(x)
        except _NLOPT_ERRORS as err:
            if error and not signals:
                raise error[0]
            exc = f"{type(err).__name__}: {err}".rstrip(": ")
    if signals:
        raise _interrupted(algorithm, signals, problem.evaluations - before)
    return x, _outcome(algorithm, opt.last_optimize_result(), exc, problem.evaluations - before)


def run_al_lbfgs(problem, x0: np.ndarray, lower: np.ndarray, upper: np.ndarray, p: float, max_evals: int,
                 state: dict, outer: int = 2) -> tuple[np.ndarray, dict]:
    """``outer`` augmented-Lagrangian iterations at exponent p within ``max_evals`` evaluations; ``state`` carries
    the multipliers ("mu") and the penalty ("rho") from one p stage to the next. Returns (end x, outcome)."""
    mu = state.setdefault("mu", {name: 0.0 for name in problem.limits.active})
    rho = state.setdefault("rho", 2e4)
    before, x, exc, code = problem.evaluations, np.clip(x0, lower, upper), None, nlopt.SUCCESS
    worst = state.get("violation", math.inf)
    for k in range(outer):
        budget = (max_evals - (problem.evaluations - before)) // (outer - k)
        if budget < 2:
            break
        weights = lambda cons: {n: max(0.0, mu[n] + rho * v) for n, v in cons.items()}  # noqa: E731
        lowest = [math.inf, x]  # the inner run's best point: where an nlopt failure leaves the search

        def merit(xv, grad):
            ev, g = problem.evaluate(xv, p, grad.size > 0, weights)
            if grad.size > 0:
                grad[:] = g
            value = ev.objective + sum((max(0.0, mu[n] + rho * v) ** 2 - mu[n] ** 2) / (2 * rho)
                                       for n, v in ev.constraints.items())
            if value < lowest[0]:
                lowest[:] = [value, xv.copy()]
            return value

        opt = nlopt.opt(nlopt.LD_LBFGS, x.size)
        opt.set_lower_bounds(lower)
        opt.set_upper_bounds(upper)
        signals: list = []  # filled by stop_requests below; the merit reads it
        opt.set_min_objective(_stoppable(merit, signals))
        opt.set_maxeval(int(budget))
        opt.set_ftol_rel(1e-14)
        opt.set_vector_storage(20)
        with stop_requests(_ON_SIGNAL, signals):
            try:
                x = opt.optimize(x)
            except nlopt.ForcedStop:
                if not signals:  # not ours (e.g. an on_eval callback's): the caller's to handle
                    raise
            except (nlopt.RoundoffLimited,) + _NLOPT_FAILURES as err:
                # LBFGS's line search at round-off, or nlopt's generic failure (a float32 merit's noise can break
                # the line search's descent test): go on from the inner run's best point
                exc = f"{type(err).__name__}: {err}".rstrip(": ")
                x = lowest[1]
        if signals:
            raise _interrupted("AL_LBFGS", signals, problem.evaluations - before)
        code = opt.last_optimize_result()
        ev, _ = problem.evaluate(x, p, False)
        for n, v in ev.constraints.items():
            mu[n] = max(0.0, mu[n] + rho * v)
        if ev.violation > 0.25 * worst:
            rho = min(rho * 4, 1e9)
        worst = ev.violation
    state.update(mu=mu, rho=rho, violation=worst)
    return x, _outcome("AL_LBFGS", code, exc, problem.evaluations - before)


def run_stages(problem, algorithm: str, x0: np.ndarray, bounds: tuple[np.ndarray, np.ndarray], schedule, max_evals: int,
               xtol_rel: float, ftol_rel: float) -> list[dict]:
    """``algorithm`` once per exponent p of ``schedule`` (the budget split evenly), each stage from the previous
    one's end point; returns the stages' outcomes."""
    lower, upper = bounds
    x, state, outcomes, start = x0, {}, [], problem.evaluations
    for i, p in enumerate(schedule):
        budget = (max_evals - (problem.evaluations - start)) // (len(schedule) - i)
        if budget < 1:
            break
        if algorithm == "AL_LBFGS":
            x, out = run_al_lbfgs(problem, x, lower, upper, p, budget, state)
        else:
            x, out = run_nlopt(problem, algorithm, x, lower, upper, p, budget, xtol_rel, ftol_rel)
        outcomes.append({**out, "lsr_p": p})
    return outcomes


def run_start(problem, label: str, x0: np.ndarray, bounds, algorithm: str, local_algorithm: str | None,
              schedule, max_evals: int, polish_evals: int, xtol_rel: float, ftol_rel: float) -> dict:
    """One start: ``algorithm`` under the p schedule from x0, then (global algorithms) a local polish from the
    start's best point. Returns the per-start record written to metrics.json."""
    problem.begin_start(label)
    t0, start = time.perf_counter(), problem.evaluations
    out = {"start": label, "stages": run_stages(problem, algorithm, x0, bounds, schedule, max_evals, xtol_rel,
                                                ftol_rel)}
    polish = algorithm.startswith("G") and local_algorithm and polish_evals > 0
    seed = problem.result_x(start=True)[0] if polish else None
    if seed is not None:  # None: the global stage made no evaluation, nothing to polish
        out["polish"] = run_stages(problem, local_algorithm, seed, bounds, schedule[-1:], polish_evals, xtol_rel,
                                   ftol_rel)
    best, least = problem.start_best, problem.start_least
    out.update({"evaluations": problem.evaluations - start, "seconds": time.perf_counter() - t0,
                "feasible": best is not None, "lsr": best.lsr_sampled if best else None,
                "lsr_smooth": best.lsr_smooth if best else None, "mtf_mean": best.mtf_mean if best else None,
                "restorability": best.restorability if best else None,
                "min_violation": least.violation if least else None})
    return out
