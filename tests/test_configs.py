"""Every config under conf/ composes with every experiment, and resolves (interpolations included)."""
from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from codesign.tasks import EXPERIMENTS, experiment_function
from tests.conftest import REPO_ROOT

CONF = REPO_ROOT / "conf"
EXPERIMENT_FILES = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
GROUP_OPTIONS = sorted((d.name, p.stem) for d in CONF.iterdir() if d.is_dir() and d.name != "experiment"
                       for p in d.glob("*.yaml"))


def test_every_registered_experiment_has_a_config_and_back():
    assert set(EXPERIMENT_FILES) == set(EXPERIMENTS)
    assert all(callable(experiment_function(name)) for name in EXPERIMENTS)  # every entry resolves


@pytest.mark.parametrize("experiment", EXPERIMENT_FILES)
def test_every_group_option_composes_with_every_experiment(experiment):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        for group, option in GROUP_OPTIONS:
            cfg = compose("config", overrides=[f"+experiment={experiment}", f"{group}={option}"])
            OmegaConf.to_container(cfg, resolve=True)
            assert cfg.task == experiment, (group, option)


def test_trainer_presets_size_the_run():
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cpu = compose("config", overrides=["+experiment=joint"])
        paper = compose("config", overrides=["+experiment=joint", "trainer=paper"])
    assert (cpu.model.size, cpu.data.image_size, cpu.data.padded_size) == ("cpu", 96, 128)
    assert (paper.model.size, paper.data.image_size, paper.data.padded_size) == ("paper", 256, 384)
    # the paper schedule: the full Sec. 6.2 decay (first quarter, then x0.3 every eighth)
    assert (paper.trainer.first_fraction, paper.trainer.every_fraction, paper.trainer.factor) == (0.25, 0.125, 0.3)
