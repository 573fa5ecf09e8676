"""Fixtures shared by the input tests."""
from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from codesign.train.model_setup import build_model
from tests.train._util import tiny_cfg


@pytest.fixture(scope="module")
def trained():
    """A tiny SGAN-B's checkpoint as the trainer writes it: weights, step, resolved config (the config of
    ``tiny_cfg``)."""
    cfg = tiny_cfg()
    torch.manual_seed(0)
    model = build_model(cfg)
    return {"model": model.state_dict(), "step": 4, "config": OmegaConf.to_container(cfg, resolve=True)}
