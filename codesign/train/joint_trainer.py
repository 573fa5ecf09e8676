"""The co-design trainer: the restoration trainer plus the mask, moved by the same backward pass.

The mask parameters are a third parameter group of the generator optimizer (own learning rate, betas and
schedule; learning rate 0 during the warm-up, when the mask is also taken out of the graph so that warm-up steps
cost what a frozen-mask step costs). The generator objective gains the LSR penalty; after every generator update
the mask is projected and the feasibility guard keeps its smooth LSR at or below lsr_max. A non-finite loss or
gradient skips the whole update (network and mask); an update that leaves the mask or a weight non-finite is undone
whole by the restoration trainer (``mask_rollbacks``, the earlier mask-only check, stays in the record at 0).

Under torchrun the mask is one more DistributedDataParallel module: every rank holds a replica, its gradient is
averaged with the networks', and the identical updates and guard decisions keep the replicas identical; every
logging step checks that (largest difference to rank 0, logged as distributed/mask_max_difference, reported in
metrics.json as mask_max_rank_difference, and repaired from rank 0 should it ever be non-zero).
"""
from __future__ import annotations

import logging

import torch

from codesign.train.lsr_constraint import (
    CodesignSpec,
    LSRConstraint,
    snapshot,
)
from codesign.design.merit import MetricsSpec
from codesign.train import distributed
from codesign.train.data import SimulatedData
from codesign.train.trainer import RestorationTrainer

log = logging.getLogger("codesign.joint")


class JointTrainer(RestorationTrainer):
    """Train a restorer and the camera's mask together. ``monitor``: a MaskMonitor for TensorBoard (None = no
    mask pictures)."""

    def __init__(self, model, data: SimulatedData, spec, run_dir, device, config: dict, writer=None,
                 seed: int = 0, codesign: CodesignSpec | None = None, lsr_max: float | None = None,
                 monitor=None, dist: distributed.DistContext = distributed.SINGLE,
                 lsr_p: float = MetricsSpec.lsr_p):
        self.cs = codesign or CodesignSpec()  # needed by the optimizer hooks the base constructor calls
        self.camera = data.camera
        self.mask = self.camera.mask
        self.mask_params = list(self.mask.parameters())
        super().__init__(model, data, spec, run_dir, device, config, writer, seed, dist)
        if self.mask_params:
            trainable = self.camera.trainable
            self.camera.set_trainable(True)  # DDP registers the parameters that require a gradient when wrapping
            self.camera.mask_forward = distributed.wrap(self.mask, dist, device)
            self.camera.set_trainable(trainable)
        self.mask_diff = 0.0
        self.constraint = LSRConstraint(self.cs, self.camera.system, lsr_max, lsr_p)
        self.monitor = monitor
        self.lsr = self.constraint.measure(self.mask)
        self.mask_rollbacks = 0
        self._before: list[torch.Tensor] | None = None
        self._step_info: dict = {}

    def extra_generator_groups(self) -> list[dict]:
        return [{"params": self.mask_params, "lr": self.cs.mask_lr, "betas": self.cs.mask_betas, "name": "mask"}]

    def generator_lr_factors(self) -> list:
        spec = self.spec
        return [spec.lr_factor, spec.lr_factor, lambda k: self.cs.mask_lr_factor(k, spec.steps, spec.lr_factor)]

    @property
    def mask_active(self) -> bool:
        return self.opt_g.param_groups[2]["lr"] > 0

    # ---- the step -------------------------------------------------------------------------------------------
    def train_step(self) -> dict:
        self.camera.set_trainable(self.mask_active)
        self._before = snapshot(self.mask)
        self._step_info = {}
        return super().train_step()

    def generator_losses(self, batch: dict, out: dict) -> dict:
        terms = super().generator_losses(batch, out)
        if "psf" in batch:  # mask trainable this step
            lsr = self.constraint.smooth_lsr(batch["psf"])
            terms["lsr_penalty"] = self.constraint.penalty(lsr)
            terms["generator_total"] = terms["generator_total"] + terms["lsr_penalty"]
        return terms

    def extra_parameters(self, opt) -> list:
        return self.mask_params if opt is self.opt_g and self.camera.trainable else []

    def after_update(self, opt, applied: torch.Tensor) -> None:
        if opt is not self.opt_g or not self.camera.trainable:
            return
        if not bool(applied):  # the guard below decides on the host anyway: the one sync of a mask step
            return
        self.lsr, kept = self.constraint.enforce(self.mask, self._before, self.lsr)
        self._step_info = {"mask_step_kept": kept}
        self.camera.invalidate()

    # ---- replicas and logging ------------------------------------------------------------------------------
    def replicated_parameters(self) -> list:
        return super().replicated_parameters() + self.mask_params

    def _log_step(self, terms: dict, t0: float, start: int, counted: bool = True) -> None:
        if self.dist.enabled:
            diff = self.replica_check(self.mask_params, "mask parameters", "distributed/mask_max_difference")
            self.mask_diff = max(self.mask_diff, diff)
            if diff > 0:
                self.camera.invalidate()
        super()._log_step(terms, t0, start, counted)

    def _log_scalars(self, terms: dict) -> None:
        super()._log_scalars(terms)
        if self.writer is None:
            return
        if "mask_step_kept" in self._step_info:
            self.writer.add_scalar("constraint/mask_step_kept", self._step_info["mask_step_kept"], self.step)
        self.writer.add_scalar("constraint/lsr_smooth", self.lsr, self.step)
        self.writer.add_scalar("constraint/lsr_max", self.constraint.lsr_max, self.step)
        self.writer.add_scalar("constraint/lsr_over_max", self.lsr / self.constraint.lsr_max, self.step)
        self.writer.add_scalar("constraint/guard_shortened", self.constraint.shortened, self.step)
        self.writer.add_scalar("constraint/guard_undone", self.constraint.undone, self.step)
        for k, v in self.mask.summary().items():
            self.writer.add_scalar(f"mask_params/{k}", v, self.step)

    def validate(self, images: bool) -> dict:
        metrics = super().validate(images)
        if self.monitor is not None and self.writer is not None:
            values = self.monitor.log(self.writer, self.step, self.mask, images=images)
            metrics.update({f"mask/{k}": v for k, v in values.items()})
            self.last_val = metrics
        return metrics

    def progress_extra(self, terms: dict) -> str:
        return f"  LSR {self.lsr:.4g} ({self.lsr / self.constraint.lsr_max:.3f} of max)"

    # ---- checkpoints ----------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        state = super().state_dict()
        state["mask"] = self.mask.state_dict()
        state["constraint"] = {"lsr_max": self.constraint.lsr_max, "lsr": self.lsr,
                               "shortened": self.constraint.shortened, "undone": self.constraint.undone,
                               "mask_rollbacks": self.mask_rollbacks}
        state["laser_halo"] = self.camera.halo_state()  # the far PSF's refresh schedule and source values
        return state

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.mask.load_state_dict(state["mask"])
        c = state["constraint"]
        self.lsr, self.mask_rollbacks = float(c["lsr"]), int(c["mask_rollbacks"])
        self.constraint.shortened, self.constraint.undone = int(c["shortened"]), int(c["undone"])
        self.camera.invalidate()
        self.camera.load_halo_state(state.get("laser_halo"))
