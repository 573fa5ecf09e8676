"""The network's name as configured (model.name): in the config of every model option, refused when malformed,
and a label that checkpoints written before it existed resume and warm-start without."""
from __future__ import annotations

import pytest

from codesign.config.runtime import to_container
from codesign.errors import ConfigError
from codesign.train.model_setup import build_model
from codesign.experiments.resume import check_resume_config
from tests.inputs._run import compose_cfg


@pytest.mark.parametrize("option, variant", [("sgan_b", "sgan_b"), ("sgan_f", "sgan_f"), ("sgan_b_gated", "sgan_b"),
                                             ("wiener_unet", "wiener_unet")])
def test_every_model_option_carries_its_name(option, variant):
    cfg = compose_cfg(f"model={option}", "model.size=tiny")
    assert cfg.model.name == option
    assert build_model(cfg).summary()["network"] == option and build_model(cfg).summary()["variant"] == variant


def test_a_null_name_is_the_variant_and_a_malformed_one_is_refused():
    assert build_model(compose_cfg("model=sgan_f", "model.size=tiny", "model.name=null")).summary()["network"] == \
        "sgan_f"
    with pytest.raises(ConfigError, match=r"^model.name = 'my net': must be a name of letters, digits and "
                                          r"underscores \(at most 64\), or null$"):
        build_model(compose_cfg("model=sgan_b", "model.size=tiny", "model.name='my net'"))


def test_checkpoints_written_before_the_name_resume():
    cfg = compose_cfg("+experiment=joint", "debug=smoke")
    old = to_container(cfg)
    old["model"].pop("name")
    check_resume_config(old, cfg, "trainer.resume", ("codesign",))
    old["model"]["fe_features"] += 1  # what the name's exemption must not hide
    with pytest.raises(ConfigError, match="was trained with different model"):
        check_resume_config(old, cfg, "trainer.resume", ("codesign",))
