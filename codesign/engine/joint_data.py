"""Training data for co-design: every training batch is simulated through the mask's current parameters *with*
gradient, so that one backward pass from the restoration loss reaches the mask.

mask params -> phase -> PSF (window) -> pixel kernel -> sensor image s and OTF (both differentiable)

Targets: the scene b does not depend on the mask; the irradiance target I_b = alpha_b (b * h) does, and is
detached here: it is G1's auxiliary target, and letting the mask move it would reward making the target easy to
predict rather than making the scene easy to restore (the mask is judged by the final restoration b).
While the mask is frozen (warm-up) the batch comes from the cached no-gradient path: same draws, no optics cost.
"""
from __future__ import annotations

import torch

from codesign.engine.distributed import SINGLE, DistContext
from codesign.engine.pipeline import RestorationData, mask_psf


class JointData(RestorationData):
    """RestorationData whose mask is trainable (``mask_trainable``); see the module docstring."""

    def __init__(self, cfg, device: torch.device, seed: int, dist: DistContext = SINGLE):
        super().__init__(cfg, device, seed, dist)
        self.mask_trainable = False
        self.mask_forward = self.mask  # called for the phase; the trainer puts a DDP wrapper here under torchrun

    def set_mask_trainable(self, flag: bool) -> None:
        self.mask_trainable = bool(flag)
        for p in self.mask.parameters():
            p.requires_grad_(self.mask_trainable)

    def train_batch(self, step: int) -> dict:
        """As RestorationData.train_batch; while the mask is trainable the batch also carries ``otf`` and ``psf``
        (the window PSF) with their graphs, and ``sensor`` depends on the mask."""
        if not self.mask_trainable:
            return super().train_batch(step)
        state, _, otf = mask_psf(self.system, self.mask, self.sim, self.device, self.mask_forward())  # with graph
        out = self.simulate(*self.train_draw(step), state=state)
        out["irradiance"] = out["irradiance"].detach()
        out["otf"], out["psf"] = otf, state.psf
        return out
