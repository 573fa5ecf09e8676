"""The restorer interface: what the trainer, the evaluation and the co-design need of a restoration network.

A restorer is an ``nn.Module`` that turns a sensor image (B, 1, P, P) and the system OTF on the padded grid
(P, P // 2 + 1) into a restored scene. It declares its trainable parts, computes its own loss terms, and says how
it restores; the trainer owns the optimizers, the step order (critics, then generators with the critics frozen),
EMA, schedules, mixed precision and data parallelism. A new network is one module defining a subclass with a
``kind`` (its name in ``model.kind``) and a spec dataclass; importing ``codesign.models`` registers it.

Interface (see SGAN and WienerUNet for the two implementations):
  spec                 a frozen dataclass of the architecture (checkpointed as ``model_spec``)
  generators()         modules the generator optimizer updates (EMA'd, run by ``forward_with``)
  critics()            modules the critic optimizer updates ([] when the objective has no adversarial term)
  forward_with(gens, sensor, otf) -> dict with "restored" (B, 1, P, P) and whatever the losses need
  generator_losses(batch, out, ctx) -> dict of loss terms with "generator_total"
  critic_losses(batch, out, ctx)   -> dict of loss terms with "critic_total" (only when critics() is not empty)
  prepare_training(device)         build training-only parts (e.g. a VGG loss from a weights file)
  calibrate(generators, data)      fit what is fitted rather than trained, at the end of a training (default:
                                   nothing; SGAN's model.level_head)
"""
from __future__ import annotations

import importlib
import pkgutil
from typing import Any, ClassVar, Mapping

import torch
import torch.nn as nn

from codesign.errors import ConfigError

REGISTRY: dict[str, type["Restorer"]] = {}


class TrainContext:
    """What a restorer's losses may ask of the trainer (given by the trainer; the defaults run modules plainly).

    run(module, *args): the module under the trainer's autocast, outputs back in float32 (a DDP wrapper where the
    trainer has one). critics: the training wrappers of ``critics()`` (DDP under torchrun), in the same order.
    gradient_penalty(critic, real, fake, cond): the WGAN-GP term with the trainer's random draws.
    """

    def __init__(self, critics: list[nn.Module] | None = None):
        self.critics = critics or []

    def run(self, module, *args):
        """``module(*args)``: this default runs it plainly (the trainer's context adds autocast and float32 outputs)."""
        return module(*args)

    def gradient_penalty(self, critic, real, fake, cond=None):  # pragma: no cover - trainers override it
        """The WGAN-GP term of ``critic`` between ``real`` and ``fake`` (conditioned on ``cond``); only a trainer's
        context computes it (its random draws), this default raises."""
        raise NotImplementedError


class Restorer(nn.Module):
    """Base class of the restoration networks (see the module docstring)."""

    kind: ClassVar[str] = ""
    method: ClassVar[str] = ""  # the column name in evaluation tables and metrics keys (psnr_<method>_...)
    any_size: ClassVar[bool] = False  # restores any (H, W) with the OTF on that grid (codesign/models/capture.py)
    # takes the mask as an input (the OTF), built to restore through any mask: restore / evaluate through another
    # mask than the one it was trained on without a warning (the others learn their mask into their weights)
    mask_conditioned: ClassVar[bool] = False
    spec: Any

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if cls.kind:
            REGISTRY[cls.kind] = cls

    @classmethod
    def from_config(cls, cfg: Mapping) -> "Restorer":  # pragma: no cover - abstract
        """The restorer of a ``model`` config block (its ``kind`` this class's), its spec validated."""
        raise NotImplementedError

    # ---- parts ------------------------------------------------------------------------------------------------
    def generators(self) -> list[nn.Module]:  # pragma: no cover - abstract
        """The modules the generator optimizer updates, EMA'd and passed to ``forward_with``, in a fixed order."""
        raise NotImplementedError

    def critics(self) -> list[nn.Module]:
        """The modules the critic optimizer updates; none by default (an objective without an adversarial term)."""
        return []

    @property
    def adversarial(self) -> bool:
        """Whether training runs critic updates (critics exist and the objective weights them)."""
        return bool(self.critics())

    def prepare_training(self, device: torch.device) -> None:
        """Build what only training needs (loaded weights of a perceptual loss, ...)."""

    def calibrate(self, generators: list[nn.Module], data, crops: int) -> dict:
        """Fit the parts that are fitted, not trained, on ``crops`` training-split crops of ``data`` (a
        SimulatedData; trainer.calibrate_crops), into the model and into ``generators`` (its restoring copies, e.g.
        EMA); what metrics.json records."""
        return {}

    @property
    def loss_status(self) -> str:
        """One line on optional loss terms that are on or off (metrics.json ``vgg_loss``)."""
        return "none"

    # ---- restoring ----------------------------------------------------------------------------------------------
    def forward_with(self, generators: list[nn.Module], sensor: torch.Tensor, otf: torch.Tensor) -> dict:
        """The restoration with the given generator modules (the own ones, EMA copies or training wrappers), in
        whatever mode they are in. Returns at least "restored" (B, 1, P, P)."""
        raise NotImplementedError  # pragma: no cover - abstract

    def forward(self, sensor: torch.Tensor, otf: torch.Tensor) -> dict:
        """``forward_with`` the own generators, in their current mode: at least "restored" (B, 1, P, P)."""
        return self.forward_with(self.generators(), sensor, otf)

    def restore(self, sensor: torch.Tensor, otf: torch.Tensor, generators: list[nn.Module] | None = None) -> dict:
        """``forward_with`` in eval mode (``generators``: e.g. EMA copies; default the own ones); modes restored."""
        gens = self.generators() if generators is None else generators
        modes = [g.training for g in gens]
        for g in gens:
            g.eval()
        try:
            return self.forward_with(gens, sensor, otf)
        finally:
            for g, mode in zip(gens, modes):
                g.train(mode)

    # ---- training -----------------------------------------------------------------------------------------------
    def generator_losses(self, batch: dict, out: dict, ctx: TrainContext) -> dict:  # pragma: no cover - abstract
        """The generator's loss terms for ``out`` (of ``forward_with``) against ``batch``, with "generator_total"."""
        raise NotImplementedError

    def critic_losses(self, batch: dict, out: dict, ctx: TrainContext) -> dict:  # pragma: no cover - abstract
        """The critics' loss terms for ``out`` against ``batch``, with "critic_total" (only when ``critics()`` is not
        empty)."""
        raise NotImplementedError

    # ---- reporting ----------------------------------------------------------------------------------------------
    def summary(self) -> dict:
        """Flat facts for metrics.json and the logs: variant and size at least."""
        return {"variant": self.kind, "size": getattr(self.spec, "size", "")}

    def scalars(self) -> dict[str, float]:
        """Values worth a TensorBoard curve besides the losses (e.g. learned noise powers)."""
        return {}

    def check_input_size(self, padded_size: int, key: str = "data.padded_size") -> None:
        """ConfigError naming ``key`` when the padded input is too small for the network."""


def parameter_count(module: nn.Module) -> int:
    """Number of scalar parameters of ``module`` (trainable or not)."""
    return sum(p.numel() for p in module.parameters())


def _discover() -> None:
    """Import every module of codesign.models, so that each restorer class registers its kind."""
    import codesign.models as package

    for info in pkgutil.iter_modules(package.__path__):
        importlib.import_module(f"codesign.models.{info.name}")


def restorer_kinds() -> tuple[str, ...]:
    """The registered ``model.kind`` names, sorted, after importing every module of codesign.models."""
    _discover()
    return tuple(sorted(REGISTRY))


def build_restorer(cfg: Mapping) -> Restorer:
    """The restorer of a ``model`` config block: ``kind`` picks the class (default sgan: checkpoints written
    before kinds existed hold SGAN configs without one), the class validates the rest."""
    _discover()
    kind = cfg.get("kind", "sgan")
    if kind not in REGISTRY:
        raise ConfigError("model.kind", kind, f"must be one of {', '.join(sorted(REGISTRY))}")
    return REGISTRY[kind].from_config(cfg)
