"""model.g2_base_nsr_tuned: the Wiener base of a fresh gated SGAN tuned to the mask before training.

Without a laser the untrained gated SGAN (model=sgan_b_gated) returns G2's base, the unit-DC Wiener deconvolution at
the unlasered nsr, which starts at g2_base_nsr = 0.03 for every mask and barely moves in a few hundred steps. The
right value depends on the mask: the evaluation's classical floor, tuned per mask, takes 0.01 for the main job's
designed spline and 0.03 for the published half rings, and a network left at 0.03 on the designed mask scored 1.1 dB
below that floor without a laser (docs/codesign.md Sec. 7). So the run tunes it as the floor is tuned: the grid of
the evaluation's Wiener (NSR_GRID), training-split crops simulated without a laser (never the test scenes), the least
pooled squared error after the per-image gain/offset match, scored on the network's own output.
"""
from __future__ import annotations

import logging
import math

import torch

from codesign.camera import field_of_view as centre
from codesign.train.evaluation import NSR_GRID, tune_nsr

log = logging.getLogger("codesign.train")


@torch.no_grad()
def tune_base_nsr(model, data, size: int) -> float:
    """Set the fresh ``model``'s unlasered base nsr (g2's log_nsr) from ``size`` training-split crops of ``data``
    simulated at laser_0 with the validation noise seed; returns the chosen nsr."""
    param = model.g2.log_nsr
    batch = data.preset_batch(data.validation_scenes(size), "laser_0", seed=data.validation_noise_seed)
    target = centre(batch["scene"], data.image_size)

    def outputs():  # the network's output at each nsr of the grid, the base's parameter set to it first
        for nsr in NSR_GRID:
            param.fill_(math.log(nsr))
            yield model.restore(batch["sensor"], data.otf)["restored"]

    best = tune_nsr(outputs(), target, data.image_size)
    param.fill_(math.log(best))
    log.info("the restorer's Wiener base tuned to this mask on %d training crops without a laser: nsr %.3g (from "
             "%.3g)", target.shape[0], best, model.spec.g2_base_nsr)
    return best
