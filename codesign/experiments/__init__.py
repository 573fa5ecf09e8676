"""The experiments: one thin module each (read the config, call the library, write the outputs), and here their
registry and the common run wrapper (validation, debug shrink, threads, device, error reporting). Only the entry
point (codesign/__main__.py) imports this package."""
from __future__ import annotations

import importlib
import logging
import pkgutil
import shlex
import shutil
import sys
import time
from pathlib import Path
from typing import Callable

import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from codesign.config.runtime import (
    apply_debug_overrides,
    check_logging,
    explicit_keys,
    resolve_device,
    run_spec,
    set_deterministic,
    set_threads,
)
from codesign.errors import ConfigError, OutputWriteError
from codesign.io import files as io
from codesign.optics.masks.records import check_mask_init
from codesign.optics.memory import grid_estimate
from codesign.optics.measured import MEASURED_DEFAULTS, load_measured
from codesign.optics.spec import OpticsSpec
from codesign.experiments import rundir
from codesign.experiments.protocol import Experiment
from codesign.experiments.specs import material_of
from codesign.train import distributed
from codesign.train import memory as train_memory
from codesign.signals import Interrupted, TrainingInterrupted, interruptible

log = logging.getLogger("codesign")


# Every module of this package but these support modules is an experiment: codesign.experiments.NAME runs
# +experiment=NAME through its run(cfg, run_dir, device) and declares its protocol as EXPERIMENT (protocol.py: the
# keys it reads, the files it writes, whether it resumes, trains under torchrun or takes a measured PSF, where its
# work starts, its debug=smoke shrink). Modules are imported only when their experiment runs (+experiment=psf never
# loads networks or nlopt).
_SUPPORT = ("main_job", "protocol", "resume", "rundir", "runlinks", "runlock", "runstart", "specs", "sweepdir",
            "typed_values")
EXPERIMENTS: tuple[str, ...] = tuple(sorted(m.name for m in pkgutil.iter_modules(__path__) if m.name not in _SUPPORT))


# Under debug=smoke a few evaluations on a coarse grid cannot meet a search's constraints or pass its re-check: a
# record an experiment logs with extra={"smoke_expected": True} then says so (unchanged without debug=smoke).
SMOKE_NOTE = "expected at smoke size: debug=smoke runs a few evaluations on a coarse grid; not a finding"


class _SmokeNote(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, "smoke_expected", False) and SMOKE_NOTE not in str(record.msg):
            record.msg = f"{record.msg} ({SMOKE_NOTE})"
        return True


def smoke_active(cfg: DictConfig) -> bool:
    """Whether the run is shrunk by debug=smoke (conf/debug/smoke.yaml, applied by run_experiment)."""
    debug = cfg.get("debug")
    return bool(debug) and debug.get("name") == "smoke"


def experiment_module(name: str):
    """The module of experiment ``name`` (imported on first use)."""
    return importlib.import_module(f"codesign.experiments.{name}")


def protocol(name: str) -> Experiment:
    """The declared protocol of experiment ``name`` (its module's EXPERIMENT)."""
    module = experiment_module(name)
    found = getattr(module, "EXPERIMENT", None)
    if not isinstance(found, Experiment) or not callable(getattr(module, "run", None)):
        raise TypeError(f"{module.__name__} is not an experiment: it must define EXPERIMENT = Experiment(...) and "
                        f"run(cfg, run_dir, device) (codesign/experiments/protocol.py)")
    return found


def root_keys(name: str) -> tuple[str, ...]:
    """Every root key experiment ``name`` accepts (COMMON_KEYS + its own)."""
    return protocol(name).all_root_keys


def read_keys(name: str) -> tuple[str, ...]:
    """The root keys experiment ``name`` actually reads: what debug=smoke shrinks and says it shrank."""
    return protocol(name).read_keys


def apply_debug(cfg: DictConfig, explicit: frozenset[str] = frozenset()) -> list[str]:
    """Apply ``debug`` (e.g. debug=smoke) to a composed config of ``+experiment=NAME`` as the entry point does: the
    common overrides and the experiment's own shrink, only on keys it reads, never on the ``explicit`` (typed) ones.
    Returns the keys applied. Needed after Hydra's compose API, which composes but does not shrink."""
    return apply_debug_overrides(cfg, explicit, read_keys(cfg.task), protocol(cfg.task).smoke)


def check_root_keys(cfg: DictConfig, task: str) -> None:
    """A root key the experiment does not read (e.g. +checkpoint=... on baseline, a typo added with +) is refused
    rather than ignored."""
    allowed = root_keys(task)
    extra = sorted(k for k in cfg if k not in allowed)
    if extra:
        raise ConfigError(extra[0], cfg.get(extra[0]), f"unknown key for +experiment={task}; allowed: "
                          f"{', '.join(allowed)}")


def check_measured_psf(cfg: DictConfig, task: str) -> None:
    """optics.psf_file: refused by an experiment that does not take one (its protocol's measured_psf: it computes
    the PSF of its mask); else the optics.psf_* keys and their files checked now, before any work, and the paths
    made absolute (a checkpoint's configuration then finds them from any folder)."""
    optics = cfg.get("optics")
    if optics is None:
        return
    path = optics.get("psf_file")
    takes = protocol(task).measured_psf
    if path is not None and not takes:
        takers = ", ".join(n for n in EXPERIMENTS if protocol(n).measured_psf)
        raise ConfigError("optics.psf_file", path, f"+experiment={task} computes the PSF of its mask and takes no "
                          f"measured one (a measured PSF replaces the computed one in {takers}): leave it null")
    if not takes or all(optics.get(k, v) == v for k, v in MEASURED_DEFAULTS.items()):
        return
    # the optics.psf_* values (a pitch without a file, too), then the files
    measured = load_measured(OpticsSpec.from_config(OmegaConf.to_container(optics, resolve=True)))
    if measured is None:
        return
    OmegaConf.update(cfg, "optics.psf_file", str(Path(measured.path).resolve()), merge=False)
    if measured.dark_path is not None:
        OmegaConf.update(cfg, "optics.psf_dark_file", str(Path(measured.dark_path).resolve()), merge=False)


def check_scene_spectrum(cfg: DictConfig, task: str) -> None:
    """optics.scene_spectrum is the light of the scenes a camera images: refused by an experiment that reads the
    optics but no sensor (psf, tolerance: the mask's PSF at the design wavelength and its laser lines), where it was
    ignored without a word."""
    reads = read_keys(task)
    optics = cfg.get("optics")
    if optics is None or optics.get("scene_spectrum") is None or "optics" not in reads or "sensor" in reads:
        return
    raise ConfigError("optics.scene_spectrum", OmegaConf.to_container(optics.scene_spectrum, resolve=True),
                      f"+experiment={task} computes the mask's PSF at optics.wavelength_m (and its laser lines) and "
                      f"images no scene, so it never reads the scene's spectrum: leave it null (the experiments that "
                      f"image scenes through the camera read it)")


def check_material(cfg: DictConfig, task: str) -> None:
    """material.*: its coefficients checked and its index at the design wavelength computed before any work (psf
    read it only after its PSF, for its laser lines: an index of 1e6 passed)."""
    if "material" not in read_keys(task) or cfg.get("material") is None:
        return
    material = material_of(cfg)
    wavelength = (cfg.get("optics") or {}).get("wavelength_m")
    if isinstance(wavelength, (int, float)) and not isinstance(wavelength, bool) and 1e-8 <= wavelength <= 1e-4:
        material.index(wavelength)  # an unphysical wavelength is named by the optics' own check


def check_optics_memory(cfg: DictConfig, task: str, device: torch.device) -> None:
    """The optics grids' memory (codesign/optics/memory.py) against what ``device`` has free, before anything is
    allocated: a pupil grid of 40,000 samples across passed every check, then was killed allocating 12.7 GB. An
    optics config the spec refuses is left to the experiment's own checks (their order, their messages)."""
    if "optics" not in read_keys(task) or cfg.get("optics") is None:
        return
    try:
        spec = OpticsSpec.from_config(to_plain(cfg.optics))
    except ConfigError:
        return
    need = grid_estimate(spec, double=cfg.get("precision") == "float64")
    free, source = train_memory.available_bytes(device)
    if free is None or need.bytes <= free:
        return
    gib = 2**30
    raise ConfigError(need.key, getattr(spec, need.key.split(".", 1)[1]), f"the optics grids need about "
                      f"{need.bytes / gib:.1f} GiB (a {need.pupil_n} x {need.pupil_n} pupil grid, the {need.focal_n} x "
                      f"{need.focal_n} focal window, {need.complex_name}, {need.wavelengths} wavelength(s)), more than "
                      f"the {free / gib:.1f} GiB available ({source}): raise optics.pupil_pitch_m, or lower "
                      f"optics.pupil_n, optics.focal_n or the wavelengths (optics.laser_wavelengths_m, "
                      f"optics.scene_spectrum)")


def to_plain(node) -> dict:
    """A config node as a plain dict (empty when absent)."""
    return OmegaConf.to_container(node, resolve=True) if node is not None else {}


def experiment_function(name: str) -> Callable:
    """The run(cfg, run_dir, device) of experiment ``name``."""
    return experiment_module(name).run


def _run_dir() -> Path:
    try:
        return Path(HydraConfig.get().runtime.output_dir)
    except ValueError:  # not under Hydra (tests calling run_experiment directly)
        return Path.cwd()


def _discard_empty_run_dir(run_dir: Path) -> None:
    """Remove a run dir that this run created and that holds only what this run's start wrote (Hydra's .hydra/ and
    log, the lock and marker): a run that stopped before writing anything. A run dir that existed before (recorded
    by the guard: an earlier run's folder, to resume it) is kept, with what that earlier run left put back; a folder
    holding anything older than this process (a user's app.log) is never removed."""
    if not run_dir.is_dir():
        return
    if rundir.existed_before(run_dir):
        rundir.restore_earlier(run_dir)
        return
    made = [p for p in run_dir.iterdir() if _made_by_this_start(p)]
    written = [p for p in run_dir.iterdir() if p not in made and _since_this_process(p)]
    if written or run_dir.resolve() == Path.cwd().resolve():
        return  # outputs of this run: kept with the record of how they were made
    for path in made:  # what this run's start wrote; anything older (a user's app.log) stays, and the folder with it
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
    if any(run_dir.iterdir()):
        return
    run_dir.rmdir()
    parent = run_dir.parent  # outputs/<task>/ that this run may have created
    if parent.is_dir() and not any(parent.iterdir()) and parent.resolve() != Path.cwd().resolve():
        parent.rmdir()


def _made_by_this_start(path: Path) -> bool:
    """Hydra's .hydra/ and log, the lock, the marker or a temp file, written since this process started (never a
    link, nor an older file of the same name: someone else's)."""
    if path.is_symlink() or not (path.name == ".hydra" or path.suffix == ".log" or rundir.is_own(path.name)):
        return False
    return _since_this_process(path)


def _since_this_process(path: Path) -> bool:
    return path.lstat().st_mtime >= _PROCESS_START - 1


def run_experiment(cfg: DictConfig, run_dir: Path | None = None, exit_on_error: bool = True) -> float | None:
    """Validate the common keys, apply ``debug`` shrinking, then run ``cfg.task``; config errors exit with 2 (with
    ``exit_on_error`` False, as the Python API calls it: raised as ConfigError, after the same clean-up), an output
    file that cannot be written with 1 (the earlier file is unchanged)."""
    run_dir = Path(run_dir) if run_dir is not None else _run_dir()
    ctx = distributed.current()
    if not ctx.is_main:  # rank 0 reports progress; the others only warnings (into <job>.rank<k>.log)
        logging.getLogger("codesign").setLevel(logging.WARNING)
    try:
        task, device = _prepare(cfg, run_dir, ctx)
        result = _call(task, cfg, run_dir, device)
        if ctx.is_main:
            rundir.finish_work(run_dir, task)  # last, after every output: the run counts as finished
        return result
    except ConfigError as err:
        distributed.settle(ctx)  # the same error stops every rank: let the others finish creating the run dir
        if ctx.is_main:
            _discard_empty_run_dir(run_dir)
        if not exit_on_error:
            raise
        if ctx.is_main:
            print(f"codesign: configuration error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    except OutputWriteError as err:
        print(f"codesign: output error: {err}", file=sys.stderr)
        raise SystemExit(1) from None
    except Interrupted as stop:
        if ctx.is_main:
            print(f"codesign: {interrupt_line(stop, run_dir, ctx, cfg.get('task'))}", file=sys.stderr)
        raise SystemExit(stop.exit_code) from None


def _check_task(cfg: DictConfig, ctx) -> str:
    """The experiment ``cfg.task`` names, refused when unknown or, under torchrun, when it does not train."""
    task = cfg.get("task")
    if task not in EXPERIMENTS:
        raise ConfigError("task", task, "choose an experiment with +experiment=NAME; available: "
                          + ", ".join(sorted(EXPERIMENTS)))
    if ctx.enabled and not protocol(task).distributed:
        trainers = ", ".join(n for n in EXPERIMENTS if protocol(n).distributed)
        raise ConfigError("task", task, f"does not train networks and runs in one process: start it without "
                          f"torchrun (training experiments under torchrun: {trainers})")
    return task


def _prepare(cfg: DictConfig, run_dir: Path, ctx) -> tuple[str, torch.device]:
    """Everything before an experiment's work: the task and the common keys checked, ``debug`` applied, threads,
    device and determinism set, the run directory checked writable and marked started; returns (task, device)."""
    task = _check_task(cfg, ctx)
    check_root_keys(cfg, task)
    applied = apply_debug(cfg, explicit_keys())
    if applied:
        log.info("debug=%s: applied %s", cfg.debug.name, ", ".join(applied))
    root = run_spec(cfg)
    check_logging(cfg)
    check_measured_psf(cfg, task)
    check_scene_spectrum(cfg, task)
    check_material(cfg, task)
    if "mask" in read_keys(task):  # a mask.init record read whole, and made for these optics, before any work
        check_mask_init(to_plain(cfg.get("mask")), to_plain(cfg.get("optics")))
    threads = set_threads(root.threads)
    device = resolve_device(root.device, ctx.local_rank if ctx.enabled else None)
    check_optics_memory(cfg, task, device)  # before anything allocates the grids
    deterministic = set_deterministic(root.deterministic, device)
    if ctx.is_main:  # the other ranks write nothing
        io.check_writable_dir(run_dir)  # before any work: never an hour of training, then a failed write
        io.check_output_files(run_dir, protocol(task).outputs)
    torch.manual_seed(root.seed)
    log.info("task=%s device=%s threads=%d deterministic=%s run_dir=%s%s", task, device, threads,
             "on" if deterministic else "off", run_dir,
             f" ranks={ctx.world} ({distributed.backend_name()})" if ctx.enabled else "")
    if ctx.is_main:
        removed = rundir.start_work(run_dir, task)  # from here on a killed run is an unfinished one
        if removed:
            log.info("removed %d temp file(s) a killed run left: %s", len(removed),
                     ", ".join(str(p.relative_to(run_dir)) for p in removed))
    return task, device


def _call(task: str, cfg: DictConfig, run_dir: Path, device: torch.device):
    """The experiment's run(cfg, run_dir, device), interruptible, its smoke-size records marked under debug=smoke."""
    note = _SmokeNote() if smoke_active(cfg) else None
    logger = getattr(experiment_module(task), "log", None)
    if note is not None and isinstance(logger, logging.Logger):
        logger.addFilter(note)
    try:
        with interruptible():  # SIGINT / SIGTERM: Interrupted, reported below (python -m codesign: from the start)
            return experiment_function(task)(cfg, run_dir, device)
    finally:
        if note is not None and isinstance(logger, logging.Logger):
            logger.removeFilter(note)


def resume_command(run_dir: Path, ctx) -> str:
    """The command line that continues this run: the same overrides, this run directory."""
    args = [a for a in sys.argv[1:] if not a.startswith("hydra.run.dir=")] + [f"hydra.run.dir={run_dir}"]
    launcher = f"torchrun --nproc_per_node={ctx.world} -m codesign" if ctx.enabled else "python -m codesign"
    return " ".join([launcher, *(shlex.quote(a) for a in args)])


# when this process loaded the experiments: a run folder's file changed since then was written by this run (a
# resumed run's earlier outputs are older)
_PROCESS_START = time.time()
_LISTED = 6  # the files an interrupt line names before "and N more"


def written_by_this_run(run_dir: Path) -> list[str]:
    """The output files of ``run_dir`` this process wrote (not Hydra's .hydra/, the log or hidden temp files)."""
    if not run_dir.is_dir():
        return []
    return sorted(p.name for p in run_dir.iterdir() if p.is_file() and not p.name.startswith(".")
                  and not p.name.endswith(".log") and p.stat().st_mtime >= _PROCESS_START - 1)


def interrupt_line(stop: Interrupted, run_dir: Path, ctx, task: str | None) -> str:
    """The one line an interrupted run prints after "codesign: ": a training, its checkpoint and the resume command;
    the main job between its stages, the stages it finished (reused on resume) and the resume command; any other
    run, what stopped it and the files it had finished (each complete: every write is atomic)."""
    if isinstance(stop, TrainingInterrupted):
        return f"{stop} (checkpoint {stop.checkpoint}); resume with: {resume_command(run_dir, ctx)}"
    kept = written_by_this_run(run_dir)
    shown = ", ".join(kept[:_LISTED]) + (f" and {len(kept) - _LISTED} more" if len(kept) > _LISTED else "")
    what = stop.detail or f"+experiment={task} stopped before it finished"
    stages = getattr(stop, "finished_stages", None)  # the main job's (main_job.note_finished_stages): resumable
    if stages is None:
        files = f"kept in {run_dir}: {shown}" if kept else "no output file written"
        return f"{stop.name}: {what}; {files} (the run is not finished)"
    if stages:
        done = f"finished stages kept in {run_dir}: {', '.join(stages)} (each reused when the run resumes)" + (
            f", and {shown}" if kept else "")
    else:
        done = "no stage finished, " + (f"kept: {shown}" if kept else "no output file written")
    return f"{stop.name}: {what}; {done} (the run is not finished); resume with: {resume_command(run_dir, ctx)}"


def resolved_config_yaml(cfg: DictConfig) -> str:
    """The config as YAML, interpolations resolved."""
    return OmegaConf.to_yaml(cfg, resolve=True)
