"""The optimizers of training and their guards: Adam with the weights and biases of Sec. 6.2 in separate groups,
the generators' EMA, and the guarded update (backward, clip, step) that a long run needs: a non-finite loss or
gradient skips the update, an update that leaves a weight non-finite all the same (finite gradients and a huge
step) is undone, weights and Adam moments back to their values before it.

No host-device synchronization on a GPU: a skipped update is decided on the device (Adam's fused kernel takes a
``found_inf`` flag, the protocol of torch.amp.GradScaler), and so is an undone one; the counters stay on the device
until a logging step reads them.
"""
from __future__ import annotations

import copy
import logging
import math

import torch
import torch.nn as nn

from codesign.train import distributed

log = logging.getLogger("codesign.train")


def init_weights(module: nn.Module) -> None:
    """Orthogonal weights and zero biases (Sec. 6.2); layers marked ``zero_init`` (attention output projections,
    generator output layers, skips) stay zero; norms stay at identity."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
            if getattr(m, "zero_init", False):
                continue
            nn.init.orthogonal_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)


def param_groups(modules: list[nn.Module], lr_w: float, lr_b: float) -> list[dict]:
    """The modules' weights and biases as two Adam groups (Sec. 6.2's two learning rates)."""
    weights, biases = [], []
    for mod in modules:
        for name, p in mod.named_parameters():
            (biases if name.endswith("bias") else weights).append(p)
    return [{"params": weights, "lr": lr_w, "name": "weights"}, {"params": biases, "lr": lr_b, "name": "biases"}]


def adam(groups: list[dict], betas, device: torch.device) -> torch.optim.Adam:
    """Adam with the fused kernel: one launch per step, and it honours the ``found_inf`` flag of a skipped update."""
    return torch.optim.Adam(groups, betas=betas, fused=device.type in ("cuda", "cpu"))


def set_requires_grad(modules, flag: bool) -> None:
    """Switch the gradients of every parameter of ``modules`` (modules or parameter lists) on or off."""
    for m in modules:
        for p in (m.parameters() if isinstance(m, nn.Module) else m):
            p.requires_grad_(flag)


class EMA:
    """Exponential moving average of the generators' parameters and buffers."""

    def __init__(self, modules: list[nn.Module], decay: float):
        self.decay = decay
        self.shadow = [copy.deepcopy(m).requires_grad_(False) for m in modules]

    @torch.no_grad()
    def update(self, modules: list[nn.Module], applied: torch.Tensor | None = None) -> None:
        """Move the average toward ``modules``; ``applied`` (0-dim bool on the device): whether the update being
        averaged happened (a skipped one leaves the average exactly as it was, without a host sync)."""
        weight = 1.0 - self.decay
        for s, m in zip(self.shadow, modules):
            for ps, p in zip(s.parameters(), m.parameters()):
                ps.lerp_(p, weight if applied is None else applied.to(ps.dtype) * weight)
            for bs, b in zip(s.buffers(), m.buffers()):
                bs.copy_(b)

    def state_dict(self) -> list[dict]:
        """The averaged copies' states, one per generator."""
        return [s.state_dict() for s in self.shadow]

    def load_state_dict(self, states: list[dict]) -> None:
        """Restore the averaged copies from an ``EMA.state_dict()``."""
        for s, st in zip(self.shadow, states):
            s.load_state_dict(st)


class _Undo:
    """What one optimizer's step may have to be undone to: copies of its parameters and state tensors, kept in
    buffers allocated once and refilled before each step by one fused copy, and selected back in place (a fresh
    clone of every tensor and a new tensor per selection cost 27 ms per update of the main job's 2.3M-parameter
    generators on 2 cores, this 20 ms: tests/train/test_trainer.py holds that it still undoes exactly)."""

    def __init__(self):
        self.tensors: list[torch.Tensor] = []
        self.copies: list[torch.Tensor] = []
        self.params: list[torch.Tensor] = []

    @torch.no_grad()
    def save(self, opt: torch.optim.Optimizer) -> None:
        params = [p for group in opt.param_groups for p in group["params"]]
        states = [v for p in params for v in opt.state.get(p, {}).values() if torch.is_tensor(v)]
        tensors = params + states
        same = len(tensors) == len(self.tensors) and all(a is b for a, b in zip(tensors, self.tensors))
        if same:
            torch._foreach_copy_(self.copies, [t.detach() for t in tensors])
        else:  # the first step, or the optimizer's state replaced (a resume): new buffers
            self.tensors, self.copies = tensors, [t.detach().clone() for t in tensors]
        self.params = params

    @torch.no_grad()
    def undo_if_not_finite(self, opt: torch.optim.Optimizer) -> torch.Tensor:
        """Undo the step just taken if it left any parameter non-finite: parameters and state tensors back to their
        saved values (states the step created, on the first step, back to 0: Adam's initial state). Decided and done
        on the device, without a host sync: every tensor is selected in place. Returns the 0-dim bool: undone."""
        if not self.params:
            return torch.zeros((), dtype=torch.bool)
        norms = torch._foreach_norm([p.detach() for p in self.params], float("inf"))  # NaN or inf where non-finite
        bad = ~torch.isfinite(torch.stack(norms)).all()
        for t, old in zip(self.tensors, self.copies):
            torch.where(bad, old, t.detach(), out=t.detach())
        known = {id(t) for t in self.tensors}
        for p in self.params:
            for v in opt.state.get(p, {}).values():
                if torch.is_tensor(v) and id(v) not in known:
                    torch.where(bad, torch.zeros((), dtype=v.dtype, device=v.device), v, out=v)
        return bad


class GuardedUpdate:
    """Backward, clip and step of one optimizer, with the two guards (see the module docstring), the counters of
    what they did on the device, and their report at logging steps."""

    def __init__(self, device: torch.device, grad_clip: float | None, dist: distributed.DistContext):
        self.device, self.grad_clip, self.dist = device, grad_clip, dist
        self.skips = torch.zeros(2, dtype=torch.long, device=device)  # updates skipped: non-finite loss, gradient
        self.rollbacks = torch.zeros((), dtype=torch.long, device=device)  # updates undone: non-finite weights
        self._reported = ([0, 0], 0)
        self._undo: dict[int, _Undo] = {}

    def __call__(self, opt: torch.optim.Optimizer, loss: torch.Tensor, modules, extra: list = ()) -> torch.Tensor:
        """Backward of ``loss``, clip of the ``modules``' gradients, step of ``opt``; ``extra``: parameters ``opt``
        updates beyond the modules' (a trainable mask: checked for a finite gradient, not clipped). Returns a 0-dim
        bool on the device: applied (False when skipped or undone, and then parameters and moments are as before).

        The backward always runs, even for a non-finite loss: under DDP every rank must take part in the gradient
        all-reduce, and the ranks then agree on the skip (any rank's non-finite loss skips them all)."""
        opt.zero_grad(set_to_none=True)
        loss.backward()
        params = [p for mod in modules for p in mod.parameters() if p.grad is not None]
        max_norm = self.grad_clip if self.grad_clip else math.inf
        norm = torch.nn.utils.clip_grad_norm_(params, max_norm, foreach=True)
        bad_loss = distributed.any_rank(~torch.isfinite(loss.detach()), self.dist)
        bad_grad = ~torch.isfinite(norm)
        for p in extra:
            if p.grad is not None:
                bad_grad = bad_grad | ~torch.isfinite(p.grad).all()
        skip = bad_loss | bad_grad
        self.skips += torch.stack([bad_loss, bad_grad & ~bad_loss]).long()
        undo = self._undo.setdefault(id(opt), _Undo())
        undo.save(opt)
        if opt.defaults.get("fused"):
            opt.found_inf = skip.to(torch.float32)  # torch.optim's fused-step protocol (torch.amp.GradScaler's)
            try:
                opt.step()
            finally:
                del opt.found_inf
        elif not bool(skip):  # a device without the fused kernel decides on the host
            opt.step()
        undone = undo.undo_if_not_finite(opt)
        self.rollbacks += undone.long()
        return ~skip & ~undone

    @property
    def skipped(self) -> int:
        """Updates skipped so far (reads the device counter: a host sync)."""
        return int(self.skips.sum())

    @property
    def undone(self) -> int:
        """Updates undone because they left a weight non-finite (reads the device counter: a host sync)."""
        return int(self.rollbacks)

    def report(self, step: int) -> None:
        """Warn about updates skipped or undone since the last report (reads the device counters: call at logging
        steps)."""
        counts, rollbacks = self.skips.tolist(), int(self.rollbacks)
        new = [c - r for c, r in zip(counts, self._reported[0])]
        if any(new):
            log.warning("step %d: %d update(s) skipped since the last report (%d non-finite loss, %d non-finite "
                        "gradient)", step, sum(new), new[0], new[1])
        if rollbacks > self._reported[1]:
            log.warning("step %d: %d update(s) left non-finite weights and were undone since the last report "
                        "(weights and Adam moments restored)", step, rollbacks - self._reported[1])
        self._reported = (counts, rollbacks)

    def load(self, skipped: int) -> None:
        """The skip count a checkpoint recorded (the undone ones start again from 0, as they always did)."""
        self.skips = torch.tensor([int(skipped), 0], dtype=torch.long, device=self.device)
        self._reported = (self.skips.tolist(), self._reported[1])
