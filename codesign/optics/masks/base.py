"""The one mask interface: a module with a differentiable ``phase()`` on its pupil grid and a ``project()``."""
from __future__ import annotations

import torch

from codesign.optics.grid import PupilGrid


class Mask(torch.nn.Module):
    """Base class of every pupil phase mask.

    Subclasses hold their learnable parameters and implement ``support_phase()``: the phase [rad] at the grid's
    support samples, shape (n_support,). ``phase()`` places it on the full (n, n) grid (0 outside the aperture,
    where the field is exactly zero anyway). ``project()`` clamps the parameters, in place and without autograd,
    to what can be built; the trainer calls it after each optimizer step.
    """

    def __init__(self, grid: PupilGrid):
        super().__init__()
        self.grid = grid

    def support_phase(self) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def phase(self) -> torch.Tensor:
        """Pupil phase [rad], shape (n, n), on the grid's dtype/device."""
        return self.grid.scatter(self.support_phase())

    def forward(self) -> torch.Tensor:
        """``mask()`` is ``mask.phase()``, so torch.func.functional_call can evaluate a mask at given parameters."""
        return self.phase()

    @torch.no_grad()
    def project(self) -> None:
        """Clamp parameters to the buildable set (default: nothing to clamp)."""

    def summary(self) -> dict[str, float]:
        """Flat, JSON-ready parameter values for metrics and logging."""
        return {}

    def freeze(self) -> "Mask":
        for p in self.parameters():
            p.requires_grad_(False)
        return self
