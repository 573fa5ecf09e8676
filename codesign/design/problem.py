"""A mask design problem: one evaluation of a mask's parameter vector gives the objective and every constraint,
with their gradients from torch, and the problem keeps the evaluation log and the best points.

Objective (minimized): log(smooth LSR_p) (``lsr``) or -restorability / 10 (``restorability``, dB). Constraints,
each c(x) <= 0 and each optional:
  mtf            log(floor) - log(mtf_mean)                       the MTF floor
  energy         log(floor) - log(E_w)                            the PSF energy kept in the optics window
  restorability  (floor - PSNR) / 10                              an expected-Wiener-PSNR floor [dB]
  lsr            log(LSR_p) - log(ceiling)                        an LSR ceiling (with the restorability objective)
  step           mean over neighbour pairs of relu(|wrap(dphi)| - cap)^2   the phase resolved by the pupil grid
The PSF is computed in the system's precision and the figures in float64: float32 resolves log(LSR) to ~5e-7,
which stops quasi-Newton methods early at large p. Every evaluation is logged (its parameter vector only when the
vector is small); the best feasible point is kept by its sampled LSR (or its restorability), whatever p was used.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from codesign.optics import metrics
from codesign.optics.lines import smooth_lsr


@dataclass
class Evaluation:
    """One evaluated point: its figures, objective and constraint values, feasibility; ``x`` when kept."""

    lsr_sampled: float
    lsr_smooth: float
    mtf_mean: float
    energy: float
    restorability: float | None
    objective: float
    constraints: dict[str, float]
    feasible: bool
    p: float
    label: str = ""
    x: np.ndarray | None = None

    @property
    def violation(self) -> float:
        """The largest constraint value above 0 (0 when every constraint holds)."""
        return max([0.0] + [v for v in self.constraints.values()])

    def score(self, objective: str) -> float:
        """Lower is better: the sampled LSR, or minus the restorability."""
        return self.lsr_sampled if objective == "lsr" else -float(self.restorability)


@dataclass
class Limits:
    """The constraint levels (None: off): mtf floor, energy floor, restorability floor [dB], LSR ceiling, the
    phase-step cap [rad] and the feasibility tolerance on each constraint value; step_margin: the optimizer is held
    to (1 - step_margin) x the step cap, feasibility judged at the cap itself. The step constraint is a mean squared
    excess, whose gradient vanishes at the cap: held at the cap itself, the augmented Lagrangian ended the main
    job's design with 2,290 of 249,364 neighbour steps up to 6 % over it (mean squared excess 2.7e-6 against the
    tolerance 1e-6), so every main job reported NO FEASIBLE POINT (docs/codesign.md Sec. 5)."""

    mtf: float | None = None
    energy: float | None = None
    restorability: float | None = None
    lsr: float | None = None
    step: float | None = None
    tolerance: float = 1e-6
    step_margin: float = 0.1
    active: tuple = field(default=())

    def __post_init__(self) -> None:
        self.active = tuple(k for k in ("mtf", "energy", "restorability", "lsr", "step")
                            if getattr(self, k) is not None)


class DesignProblem:
    """Evaluations of ``mask`` (any family) on ``system`` against ``limits``.

    Args:
        system: OpticalSystem; mask: the Mask whose parameters every evaluation overwrites; radial: RadialMTF;
        band: MTF band; objective: lsr | restorability; limits: Limits; restorability: a Restorability module
        and the camera whose kernels it scores (needed for the restorability objective or floor), as a pair;
        keep_x: log parameter vectors up to this size; on_eval: called with (problem, evaluation); lsr_grids: the
        focal grids of the smooth LSR (metrics.lsr_grids); lines: a LaserLines whose worst line the LSR is (the
        smooth LSR over every line's samples; None: the design wavelength's).
    """

    def __init__(self, system, mask, radial, band, objective: str, limits: Limits, restorability=None,
                 keep_x: int = 64, on_eval: Callable | None = None, lsr_grids: int = 1, lines=None):
        self.system, self.mask, self.radial, self.band = system, mask, radial, tuple(band)
        self.lsr_grids, self.lines = lsr_grids, lines
        self.objective, self.limits, self.restorability = objective, limits, restorability
        self.keep_x, self.on_eval = keep_x, on_eval
        self.records: list[Evaluation] = []
        self.best: Evaluation | None = None
        self.best_x: np.ndarray | None = None
        self.least: Evaluation | None = None  # the smallest violation so far (when nothing is feasible)
        self.least_x: np.ndarray | None = None
        self.start_best: Evaluation | None = None  # the same two for the current start (begin_start)
        self.start_best_x: np.ndarray | None = None
        self.start_least: Evaluation | None = None
        self.start_least_x: np.ndarray | None = None
        self.label = ""
        self.evaluations = 0
        inside = system.grid.aperture > 0
        self._pairs = (inside[:, 1:] & inside[:, :-1], inside[1:, :] & inside[:-1, :])

    @property
    def size(self) -> int:
        """The length of the searched parameter vector (the mask's vector_size)."""
        return self.mask.vector_size

    # ---- one evaluation -------------------------------------------------------------------------------------------
    def _figures(self, p: float) -> dict[str, torch.Tensor]:
        phase = self.mask.phase()
        psf = self.system.psf(phase, self.mask.plate_cell_m)
        h = psf.to(torch.float64)
        smooth, sampled = smooth_lsr(self.system, phase, psf, p, self.lsr_grids, self.mask.plate_cell_m, self.lines,
                                     torch.float64)
        out = {"lsr_smooth": smooth, "lsr_sampled": sampled,
               "mtf_mean": self.radial.summary(self.radial(metrics.mtf(h)), self.band)[0], "energy": h.sum()}
        if self.restorability is not None:
            module, camera = self.restorability
            kernel = camera.simulator.kernel(psf_state_of(self.system, psf))
            out["restorability"] = module(kernel)
        if self.limits.step is not None:
            cap = self.limits.step
            out["step"], out["step_held"] = self._step_excess(phase.to(torch.float64),
                                                              (cap, cap * (1 - self.limits.step_margin)))
        return out

    def _step_excess(self, phase: torch.Tensor, caps: tuple[float, ...]) -> tuple[torch.Tensor, ...]:
        """The mean squared excess of the wrapped neighbour steps over each cap in ``caps``."""
        totals, count = [phase.new_zeros(()) for _ in caps], 0
        for d, both in ((phase.diff(dim=1), self._pairs[0]), (phase.diff(dim=0), self._pairs[1])):
            step = (torch.remainder(d[both] + math.pi, 2 * math.pi) - math.pi).abs()
            totals = [t + torch.relu(step - cap).square().sum() for t, cap in zip(totals, caps)]
            count += int(both.sum())
        return tuple(t / max(count, 1) for t in totals)

    def _terms(self, fig: dict) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        lim = self.limits
        f = torch.log(fig["lsr_smooth"]) if self.objective == "lsr" else -fig["restorability"] / 10
        c = {}
        if lim.mtf is not None:
            c["mtf"] = math.log(lim.mtf) - torch.log(fig["mtf_mean"])
        if lim.energy is not None:
            c["energy"] = math.log(lim.energy) - torch.log(fig["energy"])
        if lim.restorability is not None:
            c["restorability"] = (lim.restorability - fig["restorability"]) / 10
        if lim.lsr is not None:
            c["lsr"] = torch.log(fig["lsr_smooth"]) - math.log(lim.lsr)
        if lim.step is not None:
            c["step"] = fig["step_held"]  # what the optimizer sees; feasibility is judged at the cap (evaluate)
        return f, c

    def begin_start(self, label: str) -> None:
        """A new start: its own best points are tracked from here (the overall ones go on)."""
        self.label = label
        self.start_best = self.start_best_x = self.start_least = self.start_least_x = None

    def evaluate(self, x, p: float, need_grad: bool, weights: Callable | None = None):
        """(Evaluation, gradient or None) at x. Without ``weights`` the gradient is a dict of the objective's
        ("objective") and each constraint's; with ``weights`` (a function of the constraint values giving a
        multiplier per constraint) it is the gradient of objective + sum_i weight_i constraint_i, the weights held
        constant (one backward pass)."""
        x = np.array(x, dtype=np.float64)
        self.mask.set_vector(torch.from_numpy(x))
        params = list(self.mask.parameters())
        for q in params:
            q.requires_grad_(need_grad)
            q.grad = None
        with torch.set_grad_enabled(need_grad):
            fig = self._figures(p)
            f, c = self._terms(fig)
            grad = None
            if need_grad:
                if weights is not None:
                    w = weights({k: float(v.detach()) for k, v in c.items()})
                    total = f + sum(w.get(k, 0.0) * v for k, v in c.items())
                    total.backward()
                    grad = self.mask.vector_grad().numpy()
                else:
                    grad = {}
                    names = ["objective"] + list(c)
                    for i, (name, t) in enumerate(zip(names, [f] + list(c.values()))):
                        g = torch.autograd.grad(t, params, retain_graph=i < len(names) - 1, allow_unused=True)
                        grad[name] = torch.cat([(gi if gi is not None else torch.zeros_like(q)).reshape(-1)
                                                for gi, q in zip(g, params)]).to(torch.float64).cpu().numpy()
        cons = {k: float(v.detach()) for k, v in c.items()}
        if "step" in cons:
            cons["step"] = float(fig["step"].detach())
        ev = Evaluation(float(fig["lsr_sampled"]), float(fig["lsr_smooth"].detach()), float(fig["mtf_mean"].detach()),
                        float(fig["energy"].detach()),
                        float(fig["restorability"].detach()) if "restorability" in fig else None,
                        float(f.detach()), cons, all(v <= self.limits.tolerance for v in cons.values()), p,
                        self.label, x.copy() if x.size <= self.keep_x else None)
        self._record(ev, x)
        return ev, grad

    def _record(self, ev: Evaluation, x: np.ndarray) -> None:
        self.evaluations += 1
        self.records.append(ev)
        if not all(math.isfinite(v) for v in (ev.objective, *ev.constraints.values())):
            if self.on_eval is not None:
                self.on_eval(self, ev)
            return
        for best, least in (("best", "least"), ("start_best", "start_least")):
            if ev.feasible and (getattr(self, best) is None or
                                ev.score(self.objective) < getattr(self, best).score(self.objective)):
                setattr(self, best, ev)
                setattr(self, f"{best}_x", x.copy())
            if getattr(self, least) is None or ev.violation < getattr(self, least).violation:
                setattr(self, least, ev)
                setattr(self, f"{least}_x", x.copy())
        if self.on_eval is not None:
            self.on_eval(self, ev)

    def result_x(self, start: bool = False) -> tuple[np.ndarray, bool]:
        """(parameter vector, feasible): the best feasible point (of the current start when ``start``), else the
        least violating one."""
        pre = "start_" if start else ""
        best = getattr(self, f"{pre}best")
        return (getattr(self, f"{pre}best_x"), True) if best is not None else (getattr(self, f"{pre}least_x"), False)


def psf_state_of(system, psf):
    """The simulator's PSFState of a PSF on ``system``."""
    from codesign.sensor.simulator import PSFState

    return PSFState(psf=psf, uncoded_peak=system.uncoded_peak, uncoded_energy=system.uncoded_energy)
