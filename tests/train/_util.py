"""Tiny, fast restoration and co-design setups for trainer tests: smoke optics, 48 px padded to 64, tiny SGAN."""
from __future__ import annotations

import torch
from hydra import compose, initialize_config_dir

from codesign.train.lsr_constraint import CodesignSpec, LSRConstraint
from codesign.optics.masks import published_mask_config
from codesign.design.merit import MetricsSpec
from codesign.optics import build_mask
from codesign.train.data import build_simulated_data
from codesign.train.distributed import SINGLE
from codesign.train.mask_codesign import MaskCodesign
from codesign.train.model_setup import build_model
from codesign.train.spec import TrainerSpec
from codesign.train.optim import init_weights
from codesign.train.trainer import Trainer
from tests.conftest import REPO_ROOT

CPU = torch.device("cpu")

TINY = ["optics.pupil_pitch_m=2.0e-5", "optics.focal_n=160", "data.image_size=48", "data.padded_size=64",
        "data.batch_size=2", "model.size=tiny", "trainer.val_size=2", "sensor.laser_halo=false"]


def tiny_cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=["+experiment=baseline", *TINY, *overrides])


def tiny_trainer(tmp_path, *overrides: str, seed: int = 0, device: torch.device = CPU,
                 **spec_changes) -> Trainer:
    cfg = tiny_cfg(*overrides)
    torch.manual_seed(seed)
    model = build_model(cfg)
    init_weights(model)
    data = build_simulated_data(cfg, device, seed)
    spec = TrainerSpec.from_config(dict(cfg.trainer)).replace(**spec_changes)
    return Trainer(model=model, data=data, spec=spec, run_dir=tmp_path, device=device, config={"test": 1}, seed=seed)


def joint_cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=["+experiment=joint", *TINY, *overrides])


def joint_trainer(tmp_path, *overrides: str, seed: int = 0, lsr_max: float | None = None, dist=SINGLE,
                  device: torch.device = CPU, steps: int = 4, **codesign) -> Trainer:
    cfg = joint_cfg(*overrides)
    torch.manual_seed(seed)
    model = build_model(cfg)
    init_weights(model)
    data = build_simulated_data(cfg, device, seed, dist)
    spec = TrainerSpec.from_config(dict(cfg.trainer)).replace(steps=steps, val_every=0, checkpoint_every=0,
                                                              image_every=0)
    cs = CodesignSpec.from_config({**dict(cfg.codesign), "warmup_fraction": 0.0, **codesign})
    if lsr_max is None:
        system = data.camera.system
        ref = build_mask(published_mask_config(dict(cfg.mask)), system.grid, system.spec.aperture_diameter_m)
        lsr_max = LSRConstraint(cs, system, 1.0, MetricsSpec.lsr_p).measure(ref)
    mask = MaskCodesign(camera=data.camera, spec=cs, lsr_max=lsr_max, lsr_p=MetricsSpec.lsr_p, steps=spec.steps,
                        device=device, dist=dist)
    return Trainer(model=model, data=data, spec=spec, run_dir=tmp_path, device=device, config={"test": 1}, seed=seed,
                   dist=dist, codesign=mask)
