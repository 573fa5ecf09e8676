"""What every training task builds the same way: the restorer of a config, its trainer, and the run's common
metrics."""
from __future__ import annotations

import torch
from omegaconf import DictConfig

from codesign.config.runtime import to_container
from codesign.models import build_restorer, parameter_count
from codesign.train import distributed
from codesign.train.spec import TrainerSpec
from codesign.train.trainer import Trainer


def build_model(cfg: DictConfig):
    """The restorer of ``cfg.model``, checked against the padded input size ``cfg.data.padded_size``."""
    model = build_restorer(to_container(cfg.model))
    model.check_input_size(int(cfg.data.padded_size))
    return model


def build_trainer(cfg: DictConfig, model, data, run_dir, device: torch.device, seed: int,
                  dist: distributed.DistContext = distributed.SINGLE, spec: TrainerSpec | None = None,
                  codesign=None) -> Trainer:
    """The one way a task builds its Trainer from a composed config: ``model`` trained on ``data`` under ``spec``
    (None: ``cfg.trainer``), writing into ``run_dir``, its checkpoints recording ``cfg`` whole; ``codesign``: a
    MaskCodesign when the mask trains too; ``dist``: the torchrun context."""
    spec = TrainerSpec.from_config(to_container(cfg.trainer)) if spec is None else spec
    return Trainer(model=model, data=data, spec=spec, run_dir=run_dir, device=device, config=to_container(cfg),
                   seed=seed, dist=dist, codesign=codesign)


def distributed_metrics(trainer) -> dict:
    """How a run was spread over processes, and the largest parameter difference between ranks found."""
    ctx = trainer.dist
    return {"world_size": ctx.world, "global_batch": int(trainer.data.sampler.batch_size),
            "parameters_max_rank_difference": trainer.replica_diff}


def run_metrics(model, device, data) -> dict:
    """The restorer, its size and where it ran: the keys every training or evaluation metrics.json starts with;
    the input sizes are ``data``'s (the SimulatedData it trains or is evaluated on: data.image_size, padded_size)."""
    return {**model.summary(), "device": str(device),
            "threads": torch.get_num_threads(), "torch": torch.__version__,
            "parameters_generators": sum(parameter_count(g) for g in model.generators()),
            "parameters_critics": sum(parameter_count(d) for d in model.critics()),
            "image_size": int(data.image_size), "padded_size": int(data.padded_size)}
