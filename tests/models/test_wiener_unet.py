"""The Wiener + UNet plug-in restorer: built from model=wiener_unet, trained by the same trainer as the SGAN (no
critics), evaluated by the same Evaluator, and co-designed with a trainable mask."""
from __future__ import annotations

import pytest
import torch
from hydra import compose, initialize_config_dir

from codesign.errors import ConfigError
from codesign.models import build_restorer, restorer_kinds
from codesign.models.wiener_unet import WienerUNet, WienerUNetSpec
from codesign.sensor.kernels import otf_from_kernel
from codesign.train.evaluation import Evaluator
from tests.conftest import REPO_ROOT
from tests.train._util import joint_trainer, tiny_trainer

TINY = ("model=wiener_unet", "model.size=tiny")


def test_registered_and_composed_like_any_restorer():
    assert "wiener_unet" in restorer_kinds() and "sgan" in restorer_kinds()
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["+experiment=baseline", "model=wiener_unet"])
    model = build_restorer(dict(cfg.model))
    assert isinstance(model, WienerUNet) and model.spec == WienerUNetSpec()
    assert model.critics() == [] and not model.adversarial and model.method == "wiener_unet"
    with pytest.raises(ConfigError, match=r"^model\.size = 'huge': must be one of tiny, cpu, paper$"):
        build_restorer({"kind": "wiener_unet", "size": "huge"})
    with pytest.raises(ConfigError, match=r"^model\.kind = 'vit': must be one of sgan, wiener_naf, wiener_unet$"):
        build_restorer({"kind": "vit"})


def test_identity_otf_and_zero_init_restore_a_flat_image():
    """The output layers start at zero (trainer init keeps them so): the untrained restorer returns zeros."""
    model = WienerUNet(WienerUNetSpec(size="tiny"))
    x = torch.rand(2, 1, 32, 32)
    out = model.restore(x, otf_from_kernel(torch.ones(1, 1), 32))
    assert out["restored"].shape == (2, 1, 32, 32) and float(out["restored"].abs().max()) == 0.0


def test_the_trainer_trains_it_without_critics_and_its_loss_falls(tmp_path):
    torch.manual_seed(0)
    tr = tiny_trainer(tmp_path, *TINY, "trainer.lr_weights=2e-3", "trainer.lr_biases=2e-3")
    assert tr.opt_d is None and tr.critics == []
    first = tr.train_step()
    assert set(first) == {"rec2", "generator_total", "generator_skipped"}
    for _ in range(24):
        last = tr.train_step()
    assert float(last["rec2"]) < 0.8 * float(first["rec2"])  # measured 0.50x after 25 steps
    state = tr.state_dict()
    assert state["opt_d"] is None and state["model_spec"]["kind"] == "wiener_unet"
    tr2 = tiny_trainer(tmp_path / "again", *TINY)
    tr2.load_state_dict(state)
    assert tr2.step == 25


def test_the_evaluator_scores_it_without_the_g1_published(tmp_path):
    tr = tiny_trainer(tmp_path, *TINY)
    ev = Evaluator(tr.model, tr.model.generators(), tr.data, batch_size=8)
    ev.tune(tr.data.validation_batch(2))
    assert ev.methods == ("sensor", "wiener", "wiener_unet")  # no pre-restored I_b: no g1_wiener
    scenes = tr.data.source.fixed_batch(tr.data.source.split_names("test")[:2], tr.data.camera.scene_size)
    batch = tr.data.preset_batch(scenes, "laser_1e3", seed=1)
    table = ev.score(ev.restore_all(batch), batch["scene"][..., 8:56, 8:56])
    assert set(table) == {"sensor", "wiener", "wiener_unet"} and table["wiener_unet"]["psnr"] > 0


def test_co_design_moves_the_mask_through_it(tmp_path):
    tr = joint_trainer(tmp_path, *TINY, mask_lr=0.5)
    before = [p.detach().clone() for p in tr.codesign.params]
    tr.train_step()
    assert tr.codesign.camera.trainable
    assert any(not torch.equal(a, b.detach()) for a, b in zip(before, tr.codesign.params))
