"""Hydra multirun sweeps (-m) with the basic launcher, and the optional launcher configs conf/hydra/launcher/
local_pool.yaml (joblib) and slurm.yaml (submitit). The compose tests need no plugin; the tests that launch through a
plugin run only where it is installed (pip install '.[launchers]')."""
from __future__ import annotations

import dataclasses
import importlib.util
import json
import os
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from tests.cli import run_codesign
from tests.conftest import REPO_ROOT

CONF = REPO_ROOT / "conf"
LAUNCHERS = CONF / "hydra" / "launcher"
JOBLIB_TARGET = "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"
SLURM_TARGET = "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
EXPERIMENTS = [("+experiment=mask_search",), ("+experiment=baseline", "model=sgan_e")]


def _has(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:  # hydra_plugins itself absent
        return False


def _compose(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=True)


def _without_hydra(cfg) -> dict:
    return {k: v for k, v in OmegaConf.to_container(cfg, resolve=False).items() if k != "hydra"}


def _jobs(sweep_dir: Path) -> list[Path]:
    return sorted((p for p in sweep_dir.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name))


def _overrides(job_dir: Path) -> list[str]:
    return yaml.safe_load((job_dir / ".hydra" / "overrides.yaml").read_text())


def _metrics(job_dir: Path) -> dict:
    return json.loads((job_dir / "metrics.json").read_text())


def _launcher_of(sweep_dir: Path) -> str:
    return yaml.safe_load((sweep_dir / "multirun.yaml").read_text())["hydra"]["launcher"]["_target_"]


# ---- composition (no plugin needed) ----------------------------------------------------------------------------
@pytest.mark.parametrize("experiment", EXPERIMENTS, ids=["mask_search", "baseline_sgan_e"])
def test_local_pool_composes(experiment):
    cfg = _compose("hydra/launcher=local_pool", *experiment)
    launcher = cfg.hydra.launcher
    assert cfg.hydra.runtime.choices["hydra/launcher"] == "local_pool"
    assert launcher._target_ == JOBLIB_TARGET
    assert launcher.n_jobs == 2
    assert launcher.backend == "loky"
    assert launcher.prefer == "processes"
    assert launcher.timeout is None and launcher.require is None
    assert launcher.pre_dispatch == "2*n_jobs" and launcher.batch_size == "auto"
    assert cfg.task == experiment[0].split("=")[1]
    if "model=sgan_e" in experiment:
        assert cfg.model.variant == "sgan_e"
    # the experiment's own config is unchanged by the launcher choice
    plain = _compose(*experiment)
    assert _without_hydra(cfg) == _without_hydra(plain)
    assert plain.hydra.launcher._target_.endswith("BasicLauncher")


@pytest.mark.parametrize("experiment", EXPERIMENTS, ids=["mask_search", "baseline_sgan_e"])
def test_slurm_composes(experiment):
    cfg = _compose("hydra/launcher=slurm", *experiment)
    launcher = cfg.hydra.launcher
    assert cfg.hydra.runtime.choices["hydra/launcher"] == "slurm"
    assert launcher._target_ == SLURM_TARGET
    assert launcher.partition is None
    assert launcher.timeout_min == 60
    assert (launcher.nodes, launcher.tasks_per_node, launcher.gpus_per_node) == (1, 1, 1)
    assert (launcher.cpus_per_task, launcher.mem_gb) == (4, 16)
    assert launcher.name == "codesign"
    assert launcher.max_num_timeout == 0 and launcher.array_parallelism == 256
    assert OmegaConf.to_container(launcher.additional_parameters) == {}
    # submitit's files land inside the sweep dir, one folder per SLURM job id
    folder = OmegaConf.to_container(launcher, resolve=True)["submitit_folder"]
    assert folder == f"{cfg.hydra.sweep.dir}/.submitit/%j"
    assert cfg.task == experiment[0].split("=")[1]
    if "model=sgan_e" in experiment:
        assert cfg.model.variant == "sgan_e"


def test_launcher_keys_are_overridable():
    pool = _compose("hydra/launcher=local_pool", "hydra.launcher.n_jobs=4", "+experiment=mask_search")
    assert pool.hydra.launcher.n_jobs == 4
    slurm = _compose("hydra/launcher=slurm", "hydra.launcher.partition=gpu", "hydra.launcher.timeout_min=240",
                     "hydra.launcher.gpus_per_node=0", "+hydra.launcher.additional_parameters.mail-type=END",
                     "+experiment=baseline", "model=sgan_f", "hydra.sweep.dir=/scratch/sweep")
    launcher = OmegaConf.to_container(slurm.hydra.launcher, resolve=True)
    assert (launcher["partition"], launcher["timeout_min"], launcher["gpus_per_node"]) == ("gpu", 240, 0)
    assert launcher["additional_parameters"] == {"mail-type": "END"}
    assert launcher["submitit_folder"] == "/scratch/sweep/.submitit/%j"


def test_launcher_names_do_not_shadow_the_plugins_own():
    # the plugins register hydra/launcher=joblib, submitit_local and submitit_slurm; ours must stay distinct
    assert sorted(p.stem for p in LAUNCHERS.glob("*.yaml")) == ["local_pool", "slurm"]


# The plugins' config dataclasses (1.2.0): the launchers receive every key as a keyword, so an extra or a misspelt
# key would fail only when a sweep starts. Written out here so that the check runs without the plugins too.
JOBLIB_KEYS = {"_target_", "n_jobs", "backend", "prefer", "require", "verbose", "timeout", "pre_dispatch",
               "batch_size", "temp_folder", "max_nbytes", "mmap_mode"}
SLURM_KEYS = {"_target_", "submitit_folder", "timeout_min", "cpus_per_task", "gpus_per_node", "tasks_per_node",
              "mem_gb", "nodes", "name", "stderr_to_stdout", "partition", "qos", "comment", "constraint", "exclude",
              "gres", "cpus_per_gpu", "gpus_per_task", "mem_per_gpu", "mem_per_cpu", "account", "signal_delay_s",
              "max_num_timeout", "additional_parameters", "array_parallelism", "setup"}


@pytest.mark.parametrize("name,keys", [("local_pool", JOBLIB_KEYS), ("slurm", SLURM_KEYS)])
def test_launcher_configs_have_exactly_the_plugin_fields(name, keys):
    assert set(yaml.safe_load((LAUNCHERS / f"{name}.yaml").read_text())) == keys


@pytest.mark.parametrize("module,conf_class,keys", [
    ("hydra_plugins.hydra_joblib_launcher.config", "JobLibLauncherConf", JOBLIB_KEYS),
    ("hydra_plugins.hydra_submitit_launcher.config", "SlurmQueueConf", SLURM_KEYS)])
def test_plugin_fields_match_the_installed_plugin(module, conf_class, keys):
    plugin = pytest.importorskip(module)
    assert {f.name for f in dataclasses.fields(getattr(plugin, conf_class))} == keys


@pytest.mark.skipif(_has("hydra_plugins.hydra_joblib_launcher"), reason="the joblib plugin is installed")
def test_local_pool_without_the_plugin_fails_before_any_job(tmp_path):
    sweep = tmp_path / "sweep"
    proc = run_codesign("-m", "hydra/launcher=local_pool", "+experiment=mask_search", "debug=smoke", "threads=1",
                        "search.mtf_floor=0.05,0.07", f"hydra.sweep.dir={sweep}")
    assert proc.returncode == 2
    assert ("codesign: configuration error: hydra/launcher = local_pool: needs the optional plugin "
            "hydra-joblib-launcher: pip install hydra-joblib-launcher (or pip install '.[launchers]' in the "
            "repository)") in proc.stderr
    assert "Traceback" not in proc.stderr and not sweep.exists()


# ---- real sweeps with Hydra's basic launcher (one job after the other) -----------------------------------------
@pytest.mark.slow  # 10 s: a 3-point sweep; twin: test_launcher_keys_are_overridable
def test_mask_search_floor_sweep(tmp_path):
    sweep = tmp_path / "sweep"
    proc = run_codesign("-m", "+experiment=mask_search", "debug=smoke", "threads=1", "search.mtf_floor=0.05,0.07",
                        f"hydra.sweep.dir={sweep}", timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    jobs = _jobs(sweep)
    assert [j.name for j in jobs] == ["0", "1"]
    assert (sweep / "multirun.yaml").is_file()
    assert _launcher_of(sweep).endswith("BasicLauncher")
    floors = []
    for job, floor in zip(jobs, ("0.05", "0.07")):
        assert f"search.mtf_floor={floor}" in _overrides(job)
        m = _metrics(job)
        assert m["limits"]["mtf"] == pytest.approx(float(floor))
        assert (job / "best_mask.json").is_file()
        floors.append(m["limits"]["mtf"])
    assert floors[0] != floors[1]


@pytest.mark.slow  # 8 s: a sweep; twin: test_local_pool_without_the_plugin_fails_before_any_job
def test_sweep_stops_at_a_refused_value(tmp_path):
    """A value the experiment refuses (0.7 is above the uncoded aperture's mtf_mean) is a configuration error: the
    sweep exits 2 at that job; the jobs before it keep their results, the jobs after it do not run."""
    sweep = tmp_path / "sweep"
    proc = run_codesign("-m", "+experiment=mask_search", "debug=smoke", "threads=1", "search.mtf_floor=0.05,0.7,0.06",
                        f"hydra.sweep.dir={sweep}", timeout=300)
    assert proc.returncode == 2, proc.stderr[-4000:]
    assert "configuration error: search.mtf_floor = 0.7" in proc.stderr
    assert [j.name for j in _jobs(sweep)] == ["0"]
    assert _metrics(sweep / "0")["limits"]["mtf"] == pytest.approx(0.05)


@pytest.mark.slow  # 34 s: three trainings
def test_sgan_variant_ablation_sweep(tmp_path):
    # ~30 s on one thread of a 2-core VM (3 smoke trainings + evaluations)
    sweep = tmp_path / "sweep"
    variants = ["sgan_b", "sgan_e", "sgan_f"]
    proc = run_codesign("-m", "+experiment=baseline", f"model={','.join(variants)}", "debug=smoke", "threads=1",
                        f"hydra.sweep.dir={sweep}", timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    jobs = _jobs(sweep)
    assert [j.name for j in jobs] == ["0", "1", "2"]
    for job, variant in zip(jobs, variants):
        assert f"model={variant}" in _overrides(job)
        m = _metrics(job)
        assert m["variant"] == variant
        assert m["steps"] == 4  # debug=smoke applies in every job
        assert (job / "checkpoint.pt").is_file()
    assert "fft" in _metrics(jobs[2])["loss_last"] and "fft" not in _metrics(jobs[0])["loss_last"]


# ---- through the optional plugins ------------------------------------------------------------------------------
def test_local_pool_sweep(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    sweep = tmp_path / "sweep"
    proc = run_codesign("-m", "hydra/launcher=local_pool", "+experiment=mask_search", "debug=smoke", "threads=1",
                        "search.mtf_floor=0.05,0.07", f"hydra.sweep.dir={sweep}", timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert _launcher_of(sweep) == JOBLIB_TARGET
    jobs = _jobs(sweep)
    assert [j.name for j in jobs] == ["0", "1"]
    assert [_metrics(j)["limits"]["mtf"] for j in jobs] == pytest.approx([0.05, 0.07])
    assert "Joblib.Parallel(n_jobs=2" in proc.stderr + proc.stdout


def test_local_pool_sweep_stops_at_a_refused_value(tmp_path):
    """Under local_pool a refused value also ends the sweep with exit 2, and it takes the jobs running beside it
    down with it (loky stops the pool): the value after it does not finish either."""
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    sweep = tmp_path / "sweep"
    proc = run_codesign("-m", "hydra/launcher=local_pool", "+experiment=mask_search", "debug=smoke", "threads=1",
                        "search.mtf_floor=0.05,0.7,0.06", f"hydra.sweep.dir={sweep}", timeout=300)
    assert proc.returncode == 2, proc.stderr[-4000:]
    assert "configuration error: search.mtf_floor = 0.7" in proc.stderr
    assert not (sweep / "1" / "metrics.json").exists() and not (sweep / "2" / "metrics.json").exists()


def test_submitit_local_sweep(tmp_path):
    """The submitit plugin's own local executor (hydra/launcher=submitit_local) runs the same code path as
    hydra/launcher=slurm without a cluster: pickled jobs started by submitit in their own processes."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    sweep = tmp_path / "sweep"
    proc = run_codesign("-m", "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=5",
                        "+experiment=mask_search", "debug=smoke", "threads=1", "search.mtf_floor=0.05,0.07",
                        f"hydra.sweep.dir={sweep}", timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    jobs = _jobs(sweep)
    assert [j.name for j in jobs] == ["0", "1"]
    assert [_metrics(j)["limits"]["mtf"] for j in jobs] == pytest.approx([0.05, 0.07])
    assert (sweep / ".submitit").is_dir()


def test_slurm_config_makes_a_valid_sbatch_script(tmp_path, monkeypatch):
    """Every key of conf/hydra/launcher/slurm.yaml is a parameter submitit's SLURM executor accepts (mapped the way
    the plugin's launch() maps them), and the sbatch script carries the values; checked without a cluster (a dummy
    srun on PATH satisfies submitit's check for one; nothing is submitted)."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    submitit = pytest.importorskip("submitit")
    from hydra_plugins.hydra_submitit_launcher.config import BaseQueueConf

    fake_bin = tmp_path / "bin"
    fake_bin.mkdir()
    (fake_bin / "srun").write_text("#!/bin/sh\nexit 1\n")
    (fake_bin / "srun").chmod(0o755)
    monkeypatch.setenv("PATH", f"{fake_bin}:{os.environ.get('PATH', '')}")
    cfg = _compose("hydra/launcher=slurm", "hydra.launcher.partition=gpu", "hydra.launcher.timeout_min=240",
                   "+hydra.launcher.additional_parameters.mail-type=END", "+experiment=baseline",
                   f"hydra.sweep.dir={tmp_path / 'sweep'}")
    params = OmegaConf.to_container(cfg.hydra.launcher, resolve=True)
    params.pop("_target_")
    folder = params.pop("submitit_folder")
    executor = submitit.AutoExecutor(folder=folder, cluster="slurm",
                                     slurm_max_num_timeout=params.pop("max_num_timeout"))
    base = {f.name for f in dataclasses.fields(BaseQueueConf)}
    executor.update_parameters(**{k if k in base else f"slurm_{k}": v for k, v in params.items()})
    script = executor._executor._make_submission_file_text("python -m codesign", "0")
    for line in ("--partition=gpu", "--time=240", "--gpus-per-node=1", "--cpus-per-task=4", "--mem=16GB",
                 "--nodes=1", "--ntasks-per-node=1", "--job-name=codesign", "--mail-type=END",
                 "--signal=USR2@120"):
        assert f"#SBATCH {line}" in script, line
    assert "--qos" not in script and "--account" not in script  # null keys are left out
