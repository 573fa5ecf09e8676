"""Every experiment declares its protocol as one checked object (codesign/experiments/protocol.py), and the runner,
the debug shrink and the tests derive what they need from it."""
from __future__ import annotations

import pytest

from codesign.experiments import EXPERIMENTS, experiment_module, protocol
from codesign.experiments.protocol import COMMON_KEYS, Experiment


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_experiment_declares_a_protocol_whose_first_work_exists(name):
    spec = protocol(name)
    first, _, rest = spec.first_work.partition(".")
    owner = experiment_module(name)
    assert hasattr(owner, first.removesuffix("()")), spec.first_work
    if rest and not first.endswith("()"):
        assert hasattr(getattr(owner, first), rest), spec.first_work
    assert set(spec.read_keys) <= set(spec.all_root_keys)


@pytest.mark.parametrize("bad,message", [
    (dict(summary="", first_work="run"), "Experiment.summary must be one non-empty line"),
    (dict(summary="x", first_work=""), "Experiment.first_work must name"),
    (dict(summary="x", first_work="run", root_keys=("optics",)), r"Experiment.root_keys: \['optics'\] are common keys"),
    (dict(summary="x", first_work="run", reads=("search",)), r"Experiment.reads: \['search'\] are not common keys"),
    (dict(summary="x", first_work="run", outputs=("a.png",)), "Experiment.outputs: plain file names, metrics.json"),
    (dict(summary="x", first_work="run", resumes=1), "Experiment.resumes must be true or false"),
    (dict(summary="x", first_work="run", smoke={"trainer.steps": 1}), r"Experiment.smoke shrinks keys under "
                                                                       r"\['trainer'\]"),
])
def test_a_bad_declaration_is_refused_naming_the_field(bad, message):
    with pytest.raises((TypeError, ValueError), match=message):
        Experiment(**bad)


def test_a_module_without_a_protocol_is_named(monkeypatch):
    import codesign.experiments.psf as psf

    monkeypatch.delattr(psf, "EXPERIMENT")
    with pytest.raises(TypeError, match=r"^codesign.experiments.psf is not an experiment: it must define EXPERIMENT"):
        protocol("psf")


def test_common_keys_are_the_root_configs_groups(repo_root):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(repo_root / "conf"), version_base="1.3"):
        cfg = compose("config")
    assert set(cfg) <= set(COMMON_KEYS) and set(COMMON_KEYS) - set(cfg) <= {"debug"}
