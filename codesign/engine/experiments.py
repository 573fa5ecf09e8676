"""Experiment registry and the common run wrapper (validation, debug shrink, threads, device, error reporting)."""
from __future__ import annotations

import importlib
import logging
import shutil
import sys
from pathlib import Path
from typing import Callable

import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from codesign.config import apply_debug_overrides, command_line_keys, resolve_device, set_threads
from codesign.errors import ConfigError

log = logging.getLogger("codesign")


# name -> "module:function" of its run function (cfg, run_dir, device); imported only when that experiment runs,
# so that e.g. +experiment=psf never loads the networks or nlopt.
EXPERIMENTS: dict[str, str] = {
    "psf": "codesign.engine.psf_task:run_psf",
    "simulate": "codesign.engine.simulate_task:run_simulate",
    "baseline": "codesign.engine.restoration_tasks:run_baseline",
    "evaluate": "codesign.engine.restoration_tasks:run_evaluate",
    "restore": "codesign.engine.restore_task:run_restore",
    "joint": "codesign.engine.joint_task:run_joint",
    "mask_search": "codesign.engine.search_task:run_mask_search",
}


def experiment_function(name: str) -> Callable:
    module, func = EXPERIMENTS[name].split(":")
    return getattr(importlib.import_module(module), func)


def _run_dir() -> Path:
    try:
        return Path(HydraConfig.get().runtime.output_dir)
    except ValueError:  # not under Hydra (tests calling run_experiment directly)
        return Path.cwd()


def explicit_keys() -> frozenset[str]:
    """Dotted keys typed on the command line of this Hydra run (empty outside Hydra)."""
    try:
        return command_line_keys(list(HydraConfig.get().overrides.task))
    except ValueError:
        return frozenset()


def _discard_empty_run_dir(run_dir: Path) -> None:
    """Remove a run dir that holds only Hydra's own files (a run that stopped before writing anything)."""
    if not run_dir.is_dir():
        return
    ours = [p for p in run_dir.iterdir() if p.name != ".hydra" and not p.name.endswith(".log")]
    if not ours and run_dir.resolve() != Path.cwd().resolve():
        shutil.rmtree(run_dir, ignore_errors=True)
        parent = run_dir.parent  # outputs/<task>/ that this run may have created
        if parent.is_dir() and not any(parent.iterdir()) and parent.resolve() != Path.cwd().resolve():
            parent.rmdir()


def run_experiment(cfg: DictConfig, run_dir: Path | None = None) -> float | None:
    """Validate the common keys, apply ``debug`` shrinking, then run ``cfg.task``; config errors exit with 2."""
    run_dir = Path(run_dir) if run_dir is not None else _run_dir()
    try:
        task = cfg.get("task")
        if task not in EXPERIMENTS:
            raise ConfigError("task", task, "choose an experiment with +experiment=NAME; available: "
                              + ", ".join(sorted(EXPERIMENTS)))
        applied = apply_debug_overrides(cfg, explicit_keys())
        if applied:
            log.info("debug=%s: applied %s", cfg.debug.name, ", ".join(applied))
        threads = set_threads(cfg.get("threads"))
        device = resolve_device(cfg.get("device", "auto"))
        torch.manual_seed(int(cfg.get("seed", 0)))
        log.info("task=%s device=%s threads=%d run_dir=%s", task, device, threads, run_dir)
        return experiment_function(task)(cfg, run_dir, device)
    except ConfigError as err:
        _discard_empty_run_dir(run_dir)
        print(f"codesign: configuration error: {err}", file=sys.stderr)
        raise SystemExit(2) from None


def resolved_config_yaml(cfg: DictConfig) -> str:
    return OmegaConf.to_yaml(cfg, resolve=True)
