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

from codesign.config import (apply_debug_overrides, check_logging, check_seed, command_line_keys, resolve_device,
                             set_threads)
from codesign.engine import distributed, io, rundir
from codesign.errors import ConfigError, OutputWriteError

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


# Root keys every experiment has (conf/config.yaml and its groups), and those its conf/experiment/NAME.yaml adds.
COMMON_KEYS = ("task", "seed", "device", "threads", "optics", "mask", "sensor", "model", "data", "trainer", "logging",
               "evaluate", "debug")
TASK_KEYS: dict[str, tuple[str, ...]] = {
    "psf": ("precision", "mtf_band", "lsr_smooth_p", "timing_repeats"),
    "simulate": ("precision", "simulate"),
    "baseline": (),
    "evaluate": ("checkpoint",),
    "restore": ("input", "checkpoint"),
    "joint": ("codesign",),
    "mask_search": ("search",),
}


# Experiments that train networks and so run data-parallel under torchrun; the others run in one process.
DISTRIBUTED_TASKS = ("baseline", "joint")


def check_root_keys(cfg: DictConfig, task: str) -> None:
    """A root key the experiment does not read (e.g. +checkpoint=... on baseline, a typo added with +) is refused
    rather than ignored."""
    allowed = COMMON_KEYS + TASK_KEYS[task]
    extra = sorted(k for k in cfg if k not in allowed)
    if extra:
        raise ConfigError(extra[0], cfg.get(extra[0]), f"unknown key for +experiment={task}; allowed: "
                          f"{', '.join(allowed)}")


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
    """Remove a run dir that this run created and that holds only Hydra's own files (a run that stopped before
    writing anything). A run dir that existed before (hydra.run.dir of an earlier run, to resume it) is kept,
    with the .hydra/ files of that earlier run put back."""
    if not run_dir.is_dir():
        return
    if rundir.existed_before(run_dir):
        rundir.restore_earlier(run_dir)
        return
    ours = [p for p in run_dir.iterdir() if p.name != ".hydra" and not p.name.endswith(".log")]
    if not ours and run_dir.resolve() != Path.cwd().resolve():
        shutil.rmtree(run_dir, ignore_errors=True)
        parent = run_dir.parent  # outputs/<task>/ that this run may have created
        if parent.is_dir() and not any(parent.iterdir()) and parent.resolve() != Path.cwd().resolve():
            parent.rmdir()


def run_experiment(cfg: DictConfig, run_dir: Path | None = None) -> float | None:
    """Validate the common keys, apply ``debug`` shrinking, then run ``cfg.task``; config errors exit with 2, an
    output file that cannot be written with 1 (the earlier file is unchanged)."""
    run_dir = Path(run_dir) if run_dir is not None else _run_dir()
    ctx = distributed.current()
    if not ctx.is_main:  # rank 0 reports progress; the others only warnings (into <job>.rank<k>.log)
        logging.getLogger("codesign").setLevel(logging.WARNING)
    try:
        task = cfg.get("task")
        if task not in EXPERIMENTS:
            raise ConfigError("task", task, "choose an experiment with +experiment=NAME; available: "
                              + ", ".join(sorted(EXPERIMENTS)))
        if ctx.enabled and task not in DISTRIBUTED_TASKS:
            raise ConfigError("task", task, f"does not train networks and runs in one process: start it without "
                              f"torchrun (training experiments under torchrun: {', '.join(DISTRIBUTED_TASKS)})")
        check_root_keys(cfg, task)
        applied = apply_debug_overrides(cfg, explicit_keys())
        if applied:
            log.info("debug=%s: applied %s", cfg.debug.name, ", ".join(applied))
        seed = check_seed(cfg)
        check_logging(cfg)
        threads = set_threads(cfg.get("threads"))
        device = resolve_device(cfg.get("device", "auto"), ctx.local_rank if ctx.enabled else None)
        if ctx.is_main:  # the other ranks write nothing
            io.check_writable_dir(run_dir)  # before any work: never an hour of training, then a failed write
        torch.manual_seed(seed)
        log.info("task=%s device=%s threads=%d run_dir=%s%s", task, device, threads, run_dir,
                 f" ranks={ctx.world} ({distributed.backend_name()})" if ctx.enabled else "")
        return experiment_function(task)(cfg, run_dir, device)
    except ConfigError as err:
        distributed.settle(ctx)  # the same error stops every rank: let the others finish creating the run dir
        if ctx.is_main:
            _discard_empty_run_dir(run_dir)
            print(f"codesign: configuration error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    except OutputWriteError as err:
        print(f"codesign: output error: {err}", file=sys.stderr)
        raise SystemExit(1) from None


def resolved_config_yaml(cfg: DictConfig) -> str:
    return OmegaConf.to_yaml(cfg, resolve=True)
