"""Settings of co-design (``codesign.*``) and the laser-protection constraint on the learned mask.

The constraint is smooth LSR <= lsr_max, where smooth LSR = ||h||_p / h0(0) >= max(h) / h0(0) (so it also bounds the
sampled LSR), and lsr_max defaults to the published mask's own smooth LSR at the same p: co-design may rearrange
the PSF but never let more laser through than the published design. Two mechanisms, both on by default:

  penalty  w * relu(lsr / lsr_max - (1 - margin))^2, added to the generator objective, steers the mask back
           inside before the boundary is reached (margin: relative distance kept from it);
  guard    after each mask update, the smooth LSR of the new parameters is measured; if it exceeds
           max(lsr_max, the previous value), the update is shortened by halving along the segment from the
           previous parameters (guard_halvings times), or undone. Feasibility is therefore kept at every step,
           not only on average; a start above lsr_max can only move down.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import torch

from codesign.config.store import register, spec_node
from codesign.errors import ConfigError, require_choice, require_number
from codesign.optics.lines import smooth_lsr
from codesign.spec_base import SpecMixin

SCHEDULES = ("constant", "trainer", "cosine")
PROTOCOLS = ("codesign", "single")


def published_fraction(value) -> float | None:
    """The share of the published mask's LSR that ``value`` names: published -> 1, published/K -> 1 / K (K > 1);
    None for anything else."""
    if value == "published":
        return 1.0
    if not isinstance(value, str) or not value.startswith("published/"):
        return None
    try:
        k = float(value[len("published/"):])
    except ValueError:
        return None
    return 1.0 / k if math.isfinite(k) and k > 1 else None


@dataclass(frozen=True)
class CodesignSpec(SpecMixin):
    """protocol: codesign (the main job: a design stage, the restorer trained on the designed and on the published
    mask, then joint, designed-frozen and published arms fine-tuned from them; codesign/experiments/main_job.py) |
    single (one joint training of the configured mask from the start, with its published comparison: the study's
    arms, the GPU runs). design: the mask family the codesign protocol's design stage searches (search.*), starting
    from the published system; null = no design stage: the configured mask is the start (mask=halfring: the
    published half rings). finetune_steps: the steps of each arm after the restorer's trainer.steps (codesign
    protocol).
    lsr_max: the LSR ceiling. Under the codesign protocol it bounds the certified (true) peak of the designed and
    the co-designed mask (the design stage's search.lsr_ceiling, the joint stage's peak guard): null = a quarter of
    the published mask's with a design stage, the published mask's without; under the single protocol it bounds the
    smooth LSR: null = the published mask's smooth LSR; start = the start mask's own, so a searched design can only
    improve (p of the smooth LSR: metrics.lsr_p). Either protocol takes a number in (0, 1], published (the published
    mask's) or published/K (K > 1: its K-th part).
    peak_max: a ceiling on the certified peak LSR that the guard also keeps after every mask update (null: none;
    the codesign protocol's joint stage sets it to lsr_max).
    penalty_weight, margin: the penalty (0 weight = off); guard, guard_halvings, guard_tolerance: the
    feasibility guard (relative tolerance on lsr_max).
    mask_lr: Adam learning rate of the mask parameters (units of the parameters per step: r_n in lambda f / W_a,
    theta_n and freeform phase in rad; 0 = the mask stays frozen: the control arm of a fine-tuning study);
    mask_betas; mask_schedule: constant | trainer (the network's Sec. 6.2
    factors) | cosine (to zero at trainer.steps); warmup_fraction: share of the steps with the mask frozen (the
    network first learns to restore, so that the mask's gradient means something).
    compare_published: also train a network on the published mask, same steps and seed, and evaluate both.
    lsr_over: design (the smooth LSR at the design wavelength) | wavelengths (the worst over
    optics.laser_wavelengths_m, the surface made as optics.wrap_waves says in material.*; lsr_max null is then the
    published mask's worst).
    """

    protocol: str = "codesign"
    design: str | None = "spline"
    finetune_steps: int = 60
    lsr_max: float | str | None = None
    peak_max: float | None = None
    penalty_weight: float = 1.0e4
    margin: float = 0.02
    guard: bool = True
    guard_halvings: int = 8
    guard_tolerance: float = 1e-6
    mask_lr: float = 0.02
    mask_betas: tuple = (0.9, 0.999)
    mask_schedule: str = "constant"
    warmup_fraction: float = 0.25
    compare_published: bool = True
    lsr_over: str = "design"
    prefix: str = field(default="codesign", compare=False, repr=False)

    def __post_init__(self) -> None:
        p = self.prefix
        require_choice(f"{p}.protocol", self.protocol, PROTOCOLS)
        if self.design is not None:
            from codesign.optics.masks import FAMILIES
            require_choice(f"{p}.design", self.design, tuple(sorted(k for k in FAMILIES if k != "halfring")))
        require_number(f"{p}.finetune_steps", self.finetune_steps, lo=1, hi=10**7, integer=True)
        if self.lsr_max is not None and self.lsr_max != "start" and published_fraction(self.lsr_max) is None:
            if isinstance(self.lsr_max, str):
                raise ConfigError(f"{p}.lsr_max", self.lsr_max, "must be null (the protocol's default), start (the "
                                  "start mask's), published, published/K (K > 1) or a number in (0, 1]")
            require_number(f"{p}.lsr_max", self.lsr_max, lo=0, lo_open=True, hi=1)
        if self.peak_max is not None:
            require_number(f"{p}.peak_max", self.peak_max, lo=0, lo_open=True, hi=1)
        require_number(f"{p}.penalty_weight", self.penalty_weight, lo=0)
        require_number(f"{p}.margin", self.margin, lo=0, hi=0.5)
        require_number(f"{p}.guard_halvings", self.guard_halvings, lo=0, hi=60, integer=True)
        require_number(f"{p}.guard_tolerance", self.guard_tolerance, lo=0, hi=0.1)
        require_number(f"{p}.mask_lr", self.mask_lr, lo=0, hi=10)
        betas = _as_list(self.mask_betas)
        if len(betas) != 2 or not all(isinstance(b, (int, float)) and 0 <= b < 1 for b in betas):
            raise ConfigError(f"{p}.mask_betas", self.mask_betas, "must be [beta1, beta2], each in [0, 1)")
        object.__setattr__(self, "mask_betas", tuple(float(b) for b in betas))
        require_choice(f"{p}.mask_schedule", self.mask_schedule, SCHEDULES)
        require_choice(f"{p}.lsr_over", self.lsr_over, ("design", "wavelengths"))
        require_number(f"{p}.warmup_fraction", self.warmup_fraction, lo=0, hi=1, hi_open=True)
        for key in ("guard", "compare_published"):
            if not isinstance(getattr(self, key), bool):
                raise ConfigError(f"{p}.{key}", getattr(self, key), "must be true or false")

    def lsr_max_value(self, published: Callable[[], float], start: Callable[[], float] | None = None,
                      measure: str = "smooth LSR", default_share: float = 1.0) -> tuple[float, str]:
        """codesign.lsr_max as a number, and where it comes from (what metrics.json records as lsr_max_from): the
        one place the setting becomes a ceiling, for either protocol.

        A number is itself ("given"); published is ``published()``, published/K its K-th part, null
        ``default_share`` of it; start is ``start()``, the start mask's own (None: the published mask's, as
        published). ``published``, ``start``: the LSR (dimensionless) of each mask, measured only when asked;
        ``measure``: what they measure, for the label (e.g. "certified peak", "smooth LSR (worst laser line)").
        """
        if self.lsr_max == "start" and start is not None:
            return start(), f"the start mask's {measure}"
        share = default_share if self.lsr_max is None else 1.0 if self.lsr_max == "start" else \
            published_fraction(self.lsr_max)
        if share is None:
            return float(self.lsr_max), "given"
        part = "" if share == 1 else f"1/{1 / share:g} of "
        return share * published(), f"{part}the published mask's {measure}"

    def warmup_steps(self, steps: int) -> int:
        """The steps with the mask frozen at the start of ``steps`` (warmup_fraction of them, rounded)."""
        return int(round(self.warmup_fraction * steps))

    def mask_lr_factor(self, step: int, steps: int, network_factor) -> float:
        """Multiplier of mask_lr at 0-based ``step``: 0 during warm-up, then the chosen schedule."""
        w = self.warmup_steps(steps)
        if step < w:
            return 0.0
        if self.mask_schedule == "trainer":
            return network_factor(step)
        if self.mask_schedule == "cosine":
            return 0.5 * (1 + math.cos(math.pi * (step - w) / max(steps - w, 1)))
        return 1.0


def _as_list(value) -> list:
    """A config sequence (list, tuple, ListConfig) as a list; anything else as [] (then refused)."""
    return list(value) if hasattr(value, "__len__") and not isinstance(value, (str, dict)) else []


def snapshot(mask) -> list[torch.Tensor]:
    """Copies of the mask's parameters (to restore after a rejected update)."""
    return [p.detach().clone() for p in mask.parameters()]


@torch.no_grad()
def restore(mask, values: list[torch.Tensor]) -> None:
    """Write ``values`` (a ``snapshot``) back into the mask's parameters."""
    for p, v in zip(mask.parameters(), values):
        p.copy_(v)


class LSRConstraint:
    """The penalty term and the feasibility guard of a mask on an OpticalSystem (see module docstring); ``p``: the
    exponent of the smooth LSR (metrics.lsr_p); ``grids``: the focal grids it is taken over (metrics.lsr_grids);
    ``lines``: a LaserLines whose worst line it constrains (None: the design wavelength)."""

    def __init__(self, spec: CodesignSpec, system, lsr_max: float, p: float, grids: int = 1, lines=None):
        self.spec, self.system, self.lsr_max, self.p, self.grids = spec, system, float(lsr_max), float(p), grids
        self.lines = lines
        self.shortened = 0  # updates the guard shortened
        self.undone = 0  # updates the guard undid entirely
        # codesign.peak_max: the certified peak is kept too (a smooth LSR at p = 16 lets the peak itself drift: from
        # 1.05e-3 to 1.42e-3 under a held smooth LSR in the co-design study, docs/codesign.md Sec. 7)
        self.peak_max = spec.peak_max
        self.peak: float | None = None  # the certified peak LSR of the current parameters, when peak_max is set

    def smooth_lsr(self, psf: torch.Tensor, phase: torch.Tensor | None = None, cell_m: float | None = None
                   ) -> torch.Tensor:
        """The smooth LSR of the window PSF ``psf`` and, given the ``phase`` it came from, of the grids offset
        between its samples (``grids``); with ``lines``, the smooth worst case over them."""
        return smooth_lsr(self.system, phase, psf, self.p, self.grids, cell_m, self.lines)[0]

    @torch.no_grad()
    def measure(self, mask) -> float:
        """The smooth LSR of ``mask``'s current parameters (over the lines when constrained over them), without
        gradient."""
        phase = mask.phase()
        return float(self.smooth_lsr(self.system.psf(phase, mask.plate_cell_m), phase, mask.plate_cell_m))

    @torch.no_grad()
    def measure_peak(self, mask) -> float:
        """The certified continuous peak LSR of ``mask`` (codesign/optics/peak.py; the design line's)."""
        return self.system.continuous_lsr(mask.phase(), mask.plate_cell_m)

    def penalty(self, lsr: torch.Tensor) -> torch.Tensor:
        """The penalty on a smooth LSR ``lsr``: penalty_weight x relu(lsr / lsr_max - (1 - margin))^2."""
        excess = torch.relu(lsr / self.lsr_max - (1.0 - self.spec.margin))
        return self.spec.penalty_weight * excess.square()

    @torch.no_grad()
    def enforce(self, mask, previous: list[torch.Tensor], previous_lsr: float) -> tuple[float, float]:
        """Project the just-updated mask, then keep it feasible; returns (smooth LSR, step fraction kept).

        ``previous``: the parameters before the update (feasible, or the best so far for an infeasible start).
        """
        raw = snapshot(mask)
        mask.project()
        lsr = self.measure(mask)
        if not self.spec.guard:
            return lsr, 1.0
        tol = 1.0 + self.spec.guard_tolerance
        limit = max(self.lsr_max, previous_lsr) * tol
        peak_limit = None if self.peak_max is None else max(self.peak_max, self.peak or 0.0) * tol

        def feasible(value: float) -> bool:  # NaN fails both tests
            if not value <= limit:
                return False
            if peak_limit is None:
                return True
            peak = self.measure_peak(mask)
            if peak <= peak_limit:
                self.peak = peak
                return True
            return False

        if feasible(lsr):
            return lsr, 1.0
        t = 1.0
        for _ in range(self.spec.guard_halvings):
            t *= 0.5
            restore(mask, [a + t * (b - a) for a, b in zip(previous, raw)])
            mask.project()
            lsr = self.measure(mask)
            if feasible(lsr):
                self.shortened += 1
                return lsr, t
        restore(mask, previous)
        self.undone += 1
        return previous_lsr, 0.0


register("codesign", "default", spec_node(CodesignSpec))
