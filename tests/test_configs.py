"""Every config under conf/ composes with every experiment, and resolves (interpolations included)."""
from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from hydra.core.config_store import ConfigStore

from codesign.experiments import EXPERIMENTS, experiment_function, read_keys, root_keys
from tests.conftest import REPO_ROOT

CONF = REPO_ROOT / "conf"
EXPERIMENT_FILES = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
# the options of every group: YAML files under conf/ and the nodes the spec dataclasses registered
# (the codesign and search blocks belong to the joint and mask_search experiments, which include them; the
# material options to export and tolerance: test_material_options_compose_with_the_fabrication_experiments)
ROOT_GROUPS = ("optics", "mask", "sensor", "model", "data", "trainer", "metrics", "logging", "evaluate")
STORED = {(group, name.removesuffix(".yaml")) for group in ROOT_GROUPS for name in ConfigStore.instance().list(group)}
GROUP_OPTIONS = sorted({(d.name, p.stem) for d in CONF.iterdir()
                        if d.is_dir() and d.name not in ("experiment", "hydra", "material") for p in d.glob("*.yaml")}
                       | STORED)


def test_every_registered_experiment_has_a_config_and_back():
    assert set(EXPERIMENT_FILES) == set(EXPERIMENTS)
    assert all(callable(experiment_function(name)) for name in EXPERIMENTS)  # every entry resolves


def _pairs_that_can_differ(experiment: str) -> list[tuple[str, str]]:
    """The group options whose composition can depend on the experiment: of the groups it reads or its YAML names
    (its defaults list may override them); any other group's option composes the same under every experiment, so
    one experiment (psf, the lightest) takes them all."""
    text = (CONF / "experiment" / f"{experiment}.yaml").read_text()
    own = set(read_keys(experiment)) | {g for g, _ in GROUP_OPTIONS if f"/{g}" in text}
    return [(g, o) for g, o in GROUP_OPTIONS if g in own or experiment == "psf"]


@pytest.mark.parametrize("experiment", EXPERIMENT_FILES)
def test_every_group_option_composes_with_every_experiment(experiment):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        for group, option in _pairs_that_can_differ(experiment):
            cfg = compose("config", overrides=[f"+experiment={experiment}", f"{group}={option}"])
            OmegaConf.to_container(cfg, resolve=True)
            assert cfg.task == experiment, (group, option)


@pytest.mark.parametrize("experiment", [n for n in EXPERIMENTS if "material" in root_keys(n)])
def test_material_options_compose_with_the_fabrication_experiments(experiment):
    from codesign.optics.materials import Material

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        for path in sorted((CONF / "material").glob("*.yaml")):
            cfg = compose("config", overrides=[f"+experiment={experiment}", f"material={path.stem}"])
            material = Material.from_config(OmegaConf.to_container(cfg.material, resolve=True))
            assert material.name == path.stem and material.index(633e-9) > 1


def test_presets_size_the_run_and_trainers_only_schedule_it():
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cpu = compose("config", overrides=["+experiment=joint"])
        paper = compose("config", overrides=["+experiment=joint", "preset=paper", "trainer=paper"])
        schedule_only = compose("config", overrides=["+experiment=joint", "preset=joint_cpu", "trainer=paper"])
        baseline = compose("config", overrides=["+experiment=baseline"])
    assert (cpu.model.size, cpu.data.image_size, cpu.data.padded_size) == ("cpu", 96, 128)
    assert (paper.model.size, paper.data.image_size, paper.data.padded_size) == ("paper", 256, 384)
    assert (baseline.model.size, baseline.data.image_size, baseline.data.padded_size) == ("cpu", 128, 192)
    # the paper schedule: the full Sec. 6.2 decay (first quarter, then x0.3 every eighth)
    assert (paper.trainer.first_fraction, paper.trainer.every_fraction, paper.trainer.factor) == (0.25, 0.125, 0.3)
    # choosing a trainer does not resize the run
    assert (schedule_only.model.size, schedule_only.data.image_size, schedule_only.trainer.steps) == ("cpu", 96, 500000)


def test_the_main_job_trains_wiener_naf_and_any_network_can_replace_it():
    from codesign.models import build_restorer

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        joint = compose("config", overrides=["+experiment=joint"])
        gated = compose("config", overrides=["+experiment=joint", "model=sgan_b_gated"])
        other = compose("config", overrides=["+experiment=joint", "model=wiener_unet"])
        paper_net = compose("config", overrides=["+experiment=joint", "model=sgan_b"])
    model = build_restorer(OmegaConf.to_container(joint.model, resolve=True))
    # the restorer conditioned on the PSF, the shipped one's network (init.checkpoint=auto starts from it)
    assert (model.kind, model.any_size, model.adversarial, joint.init.checkpoint) == ("wiener_naf", True, False, "auto")
    gated_spec = build_restorer(OmegaConf.to_container(gated.model, resolve=True)).spec
    assert (gated_spec.g2_gate, gated_spec.target_level, gated.model.loss.adv) == (True, "scene", 1.0)
    assert joint.data.params.alpha_l_spacing == "log" and gated.data.params.alpha_l_spacing == "log"
    assert (joint.trainer.ema, joint.trainer.steps, joint.codesign.finetune_steps) == (0.99, 400, 240)
    assert build_restorer(OmegaConf.to_container(other.model, resolve=True)).kind == "wiener_unet"
    assert paper_net.model.g2_residual is False and paper_net.model.laser_gate is False

def test_group_defaults_are_the_spec_dataclasses():
    from codesign.data.scenes import DataConfig
    from codesign.models.spec import ModelSpec
    from codesign.optics import OpticsSpec
    from codesign.sensor.spec import SensorSpec
    from codesign.train.spec import TrainerSpec

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=["+experiment=psf"])
    assert OpticsSpec.from_config(dict(cfg.optics)) == OpticsSpec()
    assert SensorSpec.from_config(dict(cfg.sensor)) == SensorSpec()
    assert TrainerSpec.from_config(dict(cfg.trainer)) == TrainerSpec()
    assert ModelSpec.from_config({k: v for k, v in cfg.model.items() if k not in ("kind", "loss")}) == ModelSpec()
    assert cfg.data.image_size == DataConfig.image_size and cfg.data.batch_size == DataConfig.batch_size
    # the three disagreements of earlier versions, fixed: 384 samples across, 300 steps, validation every 25
    assert (cfg.optics.pupil_pitch_m, cfg.trainer.steps, cfg.trainer.val_every) == (9.974e-6, 300, 25)


@pytest.mark.parametrize("args, message", [
    (("+experiment=psf", "lsr_smooth_p=8"), "lsr_smooth_p was renamed: use metrics.lsr_p"),
    (("+experiment=joint", "codesign.mtf_band=[0,0.3]"), "codesign.mtf_band was renamed: use metrics.mtf_band"),
    (("+experiment=mask_search", "search.lsr_p=8"), "search.lsr_p was renamed: use metrics.lsr_p"),
    (("+experiment=joint", "trainer=paper"), "trainer=paper sets the paper's schedule only; the paper's network "
                                            "widths and image sizes are preset=paper"),
])
def test_renamed_keys_name_the_new_key(tmp_path, args, message, monkeypatch, capsys):
    """The entry point refuses them before Hydra composes (in process: the exit-code path itself is
    tests/test_entry.py's subprocess test)."""
    from codesign.__main__ import main

    monkeypatch.setattr("sys.argv", ["codesign", *args, f"hydra.run.dir={tmp_path / 'run'}"])
    with pytest.raises(SystemExit) as info:
        main()
    err = capsys.readouterr().err
    assert info.value.code == 2 and f"codesign: configuration error: {message}" in err, err
    assert not (tmp_path / "run").exists()
