"""The shipped restorer (checkpoint=pretrained, codesign/models/pretrained/): found by name, and ahead of classical
Wiener under a strong laser on built-in scenes it never trained on, through a mask no training pool held."""
from __future__ import annotations

import logging

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from codesign.train.checkpoint import PRETRAINED, PRETRAINED_DIR, load_checkpoint
from codesign.train.data import SimulatedData
from codesign.train.evaluation import eval_settings, run_evaluation
from codesign.train.resume import initial_checkpoint, load_trained
from tests.conftest import REPO_ROOT

CPU = torch.device("cpu")
HELDOUT_MASK = REPO_ROOT / "benchmarks" / "results" / "pretrained" / "heldout_mask.json"
# the network's lead over the per-condition tuned Wiener at alpha_l = 1e6 on the built-in test split through the
# held-out mask, PSNR after the gain/offset match: +2.13 dB measured with the weights of 2026-11-29 (cell, chelsea:
# 28.13 vs 26.00 dB; the sensor image 26.19; +1.19 with the weights before); the test holds about half of it
MARGIN_DB = 1.0


def test_shipped_weights_are_found_by_name_and_small():
    path = PRETRAINED_DIR / PRETRAINED["pretrained"]
    assert path.stat().st_size < 20 * 2**20  # the limit for weights in the repository
    state = load_checkpoint("pretrained")
    assert state["config"]["model"]["name"] == "sgan_b_l1"  # the main job's network
    assert len(state["config"]["data"]["masks"]) >= 3  # trained over a pool of masks
    assert (PRETRAINED_DIR / "README.md").is_file()


@pytest.fixture(scope="module")
def evaluation(tmp_path_factory):
    model, generators, cfg, _ = load_trained("pretrained", CPU)
    cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    cfg.mask = {"kind": "spline", "init": str(HELDOUT_MASK)}
    cfg.evaluate = {"scenes": "data", "split": "test", "max_scenes": 4, "laser_strengths": [1.0e6], "stages": [],
                    "tuning_size": 4}
    data = SimulatedData(cfg, CPU, 0)
    return run_evaluation(eval_settings(cfg), model, generators, data, tmp_path_factory.mktemp("eval"), 0)


def test_shipped_restorer_beats_wiener_under_a_strong_laser_through_an_unseen_mask(evaluation):
    table = evaluation["evaluation"]["laser_1e6"]
    assert table["sgan"]["psnr_matched"] >= table["wiener"]["psnr_matched"] + MARGIN_DB
    assert table["sgan"]["psnr_matched"] >= table["sensor"]["psnr_matched"] + MARGIN_DB


def test_auto_start_takes_the_shipped_restorer_only_where_it_fits(caplog):
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        main_job = compose("config", overrides=["+experiment=joint"])
        tiny = compose("config", overrides=["+experiment=joint", "model.size=tiny", "data.image_size=48",
                                            "data.padded_size=64"])
    assert initial_checkpoint("auto", main_job) == "pretrained"
    with caplog.at_level(logging.INFO, logger="codesign.train"):
        assert initial_checkpoint("auto", tiny) is None
    assert ("init.checkpoint=auto: the shipped restorer was trained with another model, data.image_size, "
            "data.padded_size than this run: the restorer starts from fresh weights") in caplog.text
    assert initial_checkpoint(None, main_job) is None
    assert initial_checkpoint("some.pt", main_job) == "some.pt"
