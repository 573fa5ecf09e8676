"""Co-design as a component of training: the camera's mask moved by the same backward pass as the restorer.

The trainer calls it at fixed points and never needs to know what a mask is:
  param_group()      the mask parameters as a group of the generator optimizer (own learning rate, betas and
                     schedule: ``lr_factor``, 0 during the warm-up);
  begin_step(step)   the mask in the graph only when its learning rate is non-zero (a warm-up step costs what a
                     frozen-mask step costs), and its parameters noted for the guard;
  loss_terms(batch)  the LSR penalty of codesign/train/lsr_constraint.py, added to the generator objective;
  trained_parameters(), after_update(applied)
                     checked for a finite gradient with the networks'; after an applied update the mask is projected
                     and the feasibility guard keeps its smooth LSR at or below lsr_max (an update that left the mask
                     or a weight non-finite is undone whole by the guarded update, codesign/train/optim.py);
  scalars(), progress(), validate(), check_replicas(), state_dict()
                     what it logs, shows, checks across ranks and checkpoints.

Under torchrun the mask is one more DistributedDataParallel module: every rank holds a replica, its gradient is
averaged with the networks', and the identical updates and guard decisions keep the replicas identical; every
logging step checks that (largest difference to rank 0, logged as distributed/mask_max_difference, reported in
metrics.json as mask_max_rank_difference, and repaired from rank 0 should it ever be non-zero).
"""
from __future__ import annotations

import torch

from codesign.train import distributed
from codesign.train.lsr_constraint import CodesignSpec, LSRConstraint, snapshot


class MaskCodesign:
    """The trainable mask of ``camera`` under ``spec`` (codesign.*) with the smooth-LSR ceiling ``lsr_max``
    (``lsr_p``, ``lsr_grids``: its exponent and focal grids, metrics.lsr_p / lsr_grids); ``steps``: the training's
    length (the warm-up and the mask's schedule); ``monitor``: a MaskMonitor for TensorBoard (None = no mask
    pictures); ``lines``: the LaserLines of codesign.lsr_over=wavelengths (None: the design wavelength)."""

    def __init__(self, *, camera, spec: CodesignSpec, lsr_max: float, lsr_p: float, steps: int, device, lsr_grids=1,
                 monitor=None, dist: distributed.DistContext = distributed.SINGLE, lines=None):
        self.camera, self.mask, self.spec, self.steps, self.dist = camera, camera.mask, spec, steps, dist
        self.params = list(self.mask.parameters())
        if self.params:
            trainable = camera.trainable
            camera.set_trainable(True)  # DDP registers the parameters that require a gradient when wrapping
            camera.mask_forward = distributed.wrap(self.mask, dist, device)
            camera.set_trainable(trainable)
        self.constraint = LSRConstraint(spec, camera.system, lsr_max, lsr_p, lsr_grids, lines)
        self.monitor = monitor
        self.lsr = self.constraint.measure(self.mask)  # smooth LSR of the current parameters
        if self.constraint.peak_max is not None:
            self.constraint.peak = self.constraint.measure_peak(self.mask)
        self.max_rank_difference = 0.0
        self.kept: float | None = None  # the share of the last mask update the guard kept
        self._before: list[torch.Tensor] = []

    # ---- the optimizer --------------------------------------------------------------------------------------------
    def param_group(self) -> dict:
        """The mask's Adam parameter group (codesign.mask_lr, mask_betas), named mask."""
        return {"params": self.params, "lr": self.spec.mask_lr, "betas": self.spec.mask_betas, "name": "mask"}

    def lr_factor(self, network_factor):
        """The mask's learning-rate factor of the (0-based) step: 0 during the warm-up, then codesign.mask_schedule
        (``network_factor``: the networks' factor, for mask_schedule=trainer)."""
        return lambda k: self.spec.mask_lr_factor(k, self.steps, network_factor)

    def active(self, step: int, network_factor) -> bool:
        """Whether the mask moves at ``step`` (its learning rate there is non-zero)."""
        return self.spec.mask_lr * self.spec.mask_lr_factor(step, self.steps, network_factor) > 0

    # ---- the step ------------------------------------------------------------------------------------------------
    def begin_step(self, active: bool) -> None:
        """Before a step: the camera's mask trainable when ``active``, its parameters kept for the guard."""
        self.camera.set_trainable(active)
        self._before = snapshot(self.mask)
        self.kept = None

    def loss_terms(self, batch: dict) -> dict:
        """{"lsr_penalty": ...} when the mask trains this step (its batch carries the window PSF), else {}."""
        if "psf" not in batch:
            return {}
        lsr = self.constraint.smooth_lsr(batch["psf"], batch.get("phase"), self.mask.plate_cell_m)
        return {"lsr_penalty": self.constraint.penalty(lsr)}

    def trained_parameters(self) -> list:
        """The mask parameters the generator step updates this step (checked for a finite gradient)."""
        return self.params if self.camera.trainable else []

    def after_update(self, applied: torch.Tensor) -> None:
        """After the generator step: project the mask and keep it feasible (the guard decides on the host: the one
        sync of a mask step). A skipped or undone update leaves nothing to do."""
        if not self.camera.trainable or not bool(applied):
            return
        self.lsr, self.kept = self.constraint.enforce(self.mask, self._before, self.lsr)
        self.camera.invalidate()

    # ---- logging and replicas ----------------------------------------------------------------------------------
    def check_replicas(self, check) -> None:
        """Under torchrun, at a logging step: ``check(params, what, tag)`` (the trainer's replica check) on the
        mask parameters."""
        if not self.dist.enabled:
            return
        diff = check(self.params, "mask parameters", "distributed/mask_max_difference")
        self.max_rank_difference = max(self.max_rank_difference, diff)
        if diff > 0:
            self.camera.invalidate()

    def scalars(self) -> dict:
        """The constraint's scalars (smooth LSR, ceiling, guard counts, the peak when held) and the mask's
        parameters, for TensorBoard."""
        c = self.constraint
        out = {"constraint/lsr_smooth": self.lsr, "constraint/lsr_max": c.lsr_max,
               "constraint/lsr_over_max": self.lsr / c.lsr_max, "constraint/guard_shortened": c.shortened,
               "constraint/guard_undone": c.undone}
        if self.kept is not None:
            out["constraint/mask_step_kept"] = self.kept
        if c.peak is not None:
            out.update({"constraint/lsr_peak": c.peak, "constraint/peak_max": c.peak_max})
        return {**out, **{f"mask_params/{k}": v for k, v in self.mask.summary().items()}}

    def progress(self) -> str:
        """The mask's part of the progress line: its smooth LSR and its share of the ceiling."""
        return f"  LSR {self.lsr:.4g} ({self.lsr / self.constraint.lsr_max:.3f} of max)"

    def validate(self, writer, step: int, images: bool) -> dict:
        """The mask's figures of merit logged to TensorBoard (with pictures when ``images``), as mask/* values."""
        if self.monitor is None or writer is None:
            return {}
        return {f"mask/{k}": v for k, v in self.monitor.log(writer, step, self.mask, images=images).items()}

    def record(self) -> dict:
        """What metrics.json reports of the mask's training."""
        c = self.constraint
        peak = {} if c.peak_max is None else {"peak_max": c.peak_max, "lsr_peak_guarded": c.peak}
        return {"mask_max_rank_difference": self.max_rank_difference, "guard_shortened": c.shortened,
                "guard_undone": c.undone, "mask_rollbacks": 0, **peak}

    # ---- checkpoints ----------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """What a checkpoint keeps of the mask: its parameters, the constraint's state and the laser halo's."""
        c = self.constraint
        return {"mask": self.mask.state_dict(),
                "constraint": {"lsr_max": c.lsr_max, "lsr": self.lsr, "shortened": c.shortened, "undone": c.undone,
                               "mask_rollbacks": 0, "peak": c.peak},
                "laser_halo": self.camera.halo_state()}  # the far PSF's refresh schedule and source values

    def load_state_dict(self, state: dict) -> None:
        """Restore a ``state_dict`` (a resumed run), the camera's cached optics refreshed."""
        self.mask.load_state_dict(state["mask"])
        c = state["constraint"]
        self.lsr = float(c["lsr"])
        self.constraint.shortened, self.constraint.undone = int(c["shortened"]), int(c["undone"])
        if c.get("peak") is not None:
            self.constraint.peak = float(c["peak"])
        self.camera.invalidate()
        self.camera.load_halo_state(state.get("laser_halo"))
