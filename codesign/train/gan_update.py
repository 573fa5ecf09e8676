"""One training update of a restorer on one batch, the whole GAN step order in one place (as BasicSR's SRGAN model
has it), for any restorer (codesign/models/restorer.py) and with or without a trainable mask:

  0. the generators run once on the batch (through their training wrappers: DDP, torch.compile);
  1. the critics (``critic_steps`` times, when the restorer is adversarial) on that pass's outputs detached, with the
     restorer's critic terms (for the SGAN: WGAN terms and gradient penalty of D1 and both D2 scales);
  2. the generators, reusing the pass (they have not changed), every critic frozen (requires_grad False), with the
     restorer's generator terms (for the SGAN: adversarial + Charbonnier L1 + MDF + VGG + FFT) and, in co-design,
     the mask's LSR term; the mask is a parameter group of the same optimizer, projected and guarded after it;
  3. the generators' EMA, when on.
Every optimizer step goes through the guarded update (codesign/train/optim.py: skip a non-finite loss or gradient,
undo a step that leaves a weight non-finite).
"""
from __future__ import annotations

import torch

from codesign.models.restorer import Restorer, TrainContext
from codesign.train.optim import EMA, GuardedUpdate, set_requires_grad


class GANUpdate:
    """The update of ``model``'s generators (``opt_g``) and critics (``opt_d``, None without critics) on a batch;
    ``ctx``: the trainer (the restorer's TrainContext: autocast, training wrappers, gradient penalty); ``data``: the
    SimulatedData (its ``otf``: the frozen mask's, for a batch that carries none);
    ``generators``: the generators' training wrappers; ``codesign``: the trainable mask's component (None: the
    mask stays frozen). Returns the loss terms as detached 0-dim tensors on the device."""

    def __init__(self, *, model: Restorer, ctx: TrainContext, data, generators: list, opt_g, opt_d,
                 guard: GuardedUpdate, ema: EMA | None, critic_steps: int, codesign=None):
        self.model, self.ctx, self.data, self.generators = model, ctx, data, generators
        self.opt_g, self.opt_d, self.guard, self.ema = opt_g, opt_d, guard, ema
        self.critic_steps, self.codesign = critic_steps, codesign

    def __call__(self, batch: dict) -> dict:
        out = self.generate(batch)
        terms = {}
        if self.opt_d is not None and self.model.adversarial:
            for _ in range(self.critic_steps):
                terms.update(self.critic_update(batch, out))
        terms.update(self.generator_update(batch, out))
        return {k: v.detach() for k, v in terms.items()}

    def generate(self, batch: dict) -> dict:
        """The generators' outputs for ``batch`` through the training wrappers, with their graph (the batch's own
        OTF when the mask is trainable, else the data's)."""
        otf = batch["otf"] if "otf" in batch else self.data.otf
        return self.ctx.run(lambda s, o: self.model.forward_with(self.generators, s, o), batch["sensor"], otf)

    def critic_update(self, batch: dict, out: dict | None = None) -> dict:
        """One critic update. ``out``: the generators' outputs for this batch (detached by the restorer's critic
        terms); None = compute them without gradient."""
        if out is None:
            with torch.no_grad():
                out = self.generate(batch)
        terms = self.model.critic_losses(batch, out, self.ctx)
        applied = self.guard(self.opt_d, terms["critic_total"], self.model.critics())
        terms["critic_skipped"] = (~applied).float()
        return terms

    def generator_losses(self, batch: dict, out: dict) -> dict:
        """The restorer's generator terms, and the mask's LSR term when it trains this step."""
        terms = self.model.generator_losses(batch, out, self.ctx)
        if self.codesign is not None:
            extra = self.codesign.loss_terms(batch)
            if extra:
                terms.update(extra)
                terms["generator_total"] = terms["generator_total"] + sum(extra.values())
        return terms

    def generator_update(self, batch: dict, out: dict | None = None) -> dict:
        """One generator (and mask) update with every critic frozen. ``out``: this batch's generator outputs with
        their graph; None = compute. The frozen critics run as plain modules (no DDP: they take no update here)."""
        crits = self.model.critics()
        set_requires_grad(crits, False)  # critics frozen: no gradient accumulates in them
        try:
            if out is None:
                out = self.generate(batch)
            terms = self.generator_losses(batch, out)
        finally:
            set_requires_grad(crits, True)
        extra = self.codesign.trained_parameters() if self.codesign is not None else []
        applied = self.guard(self.opt_g, terms["generator_total"], self.model.generators(), extra)
        if self.codesign is not None:
            self.codesign.after_update(applied)
        terms["generator_skipped"] = (~applied).float()
        if self.ema is not None:
            self.ema.update(self.model.generators(), applied)
        return terms
