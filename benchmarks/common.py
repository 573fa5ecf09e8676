"""Shared helpers of the suite's entries (benchmarks/bench_*.py): machine description, subprocess isolation for peak
memory, atomic result writing, tables and plots, timing, and the setups several entries build (Hydra configs,
the default camera with the published mask, a co-design trainer). Everything here is public: an entry imports
nothing private from another module."""
from __future__ import annotations

import datetime
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import torch

REPO = Path(__file__).resolve().parent.parent
# the main job's seed-0 design (1/4 of the published peak), which no pool of the shipped restorer held: the unseen
# mask of benchmarks.pretrain and benchmarks.pretrained_eval
HELDOUT_MASK = REPO / "benchmarks" / "results" / "pretrained" / "heldout_mask.json.gz"
RESULTS = REPO / "benchmarks" / "results"
CONF = REPO / "conf"


def mask_overrides(mask: str) -> list[str]:
    """The config overrides that image through ``mask``: ``published`` (the five half rings), ``heldout``
    (HELDOUT_MASK) or the path of a mask record."""
    from codesign.optics.masks import load_record

    if mask == "published":
        return ["mask=halfring"]
    path = HELDOUT_MASK if mask == "heldout" else Path(mask).resolve()
    return ["mask=" + load_record(path, "mask", "a mask record")["kind"], f"mask.init={path}"]


def machine() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return {
        "cpu": cpu, "cores": os.cpu_count(), "threads": torch.get_num_threads(), "torch": torch.__version__,
        "python": platform.python_version(), "date": datetime.date.today().isoformat(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }


def gpu_driver() -> str | None:
    """The NVIDIA driver's version as nvidia-smi reports it (the first GPU's), None where it cannot say."""
    try:
        q = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                           capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return q.stdout.strip().splitlines()[0] if q.returncode == 0 and q.stdout.strip() else None


def peak_rss_mb() -> float:
    """Peak resident set size of this process [MiB] (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run_isolated(module: str, args: list[str], env: dict[str, str] | None = None) -> dict:
    """Run ``python -m module args`` in a fresh process (clean peak-memory reading); it prints one JSON line.
    ``env``: variables added to this process's environment for the child (e.g. thread-pool sizes, which BLAS
    libraries read once, when they load)."""
    out = subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parent.parent, env={**os.environ, **(env or {})})
    if out.returncode != 0:
        raise RuntimeError(f"python -m {module} {' '.join(args)} failed ({out.returncode}):\n{out.stderr[-4000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


# ---- the suite interface (python -m benchmarks) ------------------------------------------------------------
# Each suite module (benchmarks/bench_*.py) defines ``run(scale: str, out: Path) -> Report``: it measures at
# scale "quick" (the whole suite 37 min on 2 CPU cores, docs/benchmarks.md) or "full", prints its tables, writes JSON
# and PNGs into ``out`` (benchmarks/results/<scale>/) and returns what docs/benchmarks.md shows.
SCALES = ("quick", "full")


@dataclass
class Report:
    """What one benchmark contributes to docs/benchmarks.md: a section title, markdown tables, figures, notes."""

    name: str
    title: str
    tables: list[str] = field(default_factory=list)  # markdown, each printed and written as-is
    figures: list[Path] = field(default_factory=list)  # PNGs under ``out``
    notes: list[str] = field(default_factory=list)  # one paragraph each (how measured, what is the default)


def run_logged(cmd: list[str], log: Path, timeout: float) -> tuple[int, float]:
    """Run ``cmd`` in the repository with its output in ``log``; (exit status, seconds); 124 on timeout."""
    t0 = time.perf_counter()
    with open(log, "w") as f:
        try:
            rc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=REPO, timeout=max(timeout, 1),
                                env={**os.environ, "PYTHONUNBUFFERED": "1"}).returncode
        except subprocess.TimeoutExpired:
            rc = 124
    return rc, time.perf_counter() - t0


def markdown_table(header: list[str], rows: list[list], fmt: dict | None = None) -> str:
    """A markdown table; floats are formatted with ``fmt[column]`` (default 4 significant digits)."""
    fmt = fmt or {}

    def cell(col: str, v) -> str:
        if isinstance(v, float):
            return format(v, fmt.get(col, ".4g"))
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(h, v) for h, v in zip(header, r)) + " |" for r in rows]
    return "\n".join(lines)


def time_error_plot(path: Path, series: dict[str, list[tuple[float, float, str]]], xlabel: str, ylabel: str,
                    title: str, logy: bool = True, hline: tuple[float, str] | None = None) -> Path:
    """Run time (x) against error (y): one marker line per series of (seconds, error, point label) tuples."""
    from codesign.io.files import save_figure
    from codesign.io.plots import plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for i, (label, pts) in enumerate(series.items()):
        pts = [p for p in pts if p[1] is not None]
        if not pts:
            continue
        xs, ys = [p[0] for p in pts], [max(p[1], 1e-17) if logy else p[1] for p in pts]
        ax.plot(xs, ys, "o-", color=f"C{i % 10}", label=label, ms=4)
        for x, y, name in zip(xs, ys, [p[2] for p in pts]):
            if name:
                ax.annotate(name, (x, y), fontsize=6, xytext=(2, 2), textcoords="offset points")
    if hline is not None:
        ax.axhline(hline[0], color="0.5", ls=":", label=hline[1])
    ax.set(xscale="log", yscale="log" if logy else "linear", xlabel=xlabel, ylabel=ylabel, title=title)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    return save_figure(path, fig)


def compact_png(path: Path) -> Path:
    """Re-save a plot (RGB or opaque RGBA) with a palette of 256 colours, atomically: its flat colours stay exact
    (white, the lines), only a few antialiased edge pixels move (mean error < 0.1 of 255), and the file takes half
    the bytes, which keeps benchmarks/results small (issue 58). Other images (grayscale photographs, transparent
    ones) stay as they are."""
    from PIL import Image

    with Image.open(path) as im:
        if im.mode not in ("RGB", "RGBA") or im.mode == "RGBA" and im.getchannel("A").getextrema()[0] < 255:
            return path
        rgb = im.convert("RGB")
    tmp = path.with_name(path.name + ".tmp")
    rgb.quantize(256, method=Image.Quantize.MEDIANCUT).save(tmp, format="PNG", optimize=True)
    os.replace(tmp, path)
    return path


def timeit(fn, repeats: int, warmup: int = 1, sync=None) -> float:
    """Median seconds of ``repeats`` calls after ``warmup`` calls (``sync()`` before each clock read on GPU)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(max(repeats, 1)):
        if sync:
            sync()
        t0 = time.perf_counter()
        fn()
        if sync:
            sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def cuda_sync(dev):
    """``timeit``'s sync for a device: torch.cuda.synchronize on a GPU, None on the CPU."""
    return torch.cuda.synchronize if dev.type == "cuda" else None


def peak_cuda_mib(dev, reset: bool = False) -> float | None:
    """Peak allocated CUDA memory [MiB] since the last reset (``reset=True`` resets it first); None on the CPU."""
    if dev.type != "cuda":
        return None
    if reset:
        torch.cuda.reset_peak_memory_stats()
    return torch.cuda.max_memory_allocated() / 2**20


def write_text(path: Path, text: str) -> Path:
    """Atomic text write (temp file, then rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
    return path


def write_json(path: Path, data: dict) -> Path:
    """Atomic JSON write."""
    return write_text(path, json.dumps(data, indent=2) + "\n")


def finish(rep: Report, out: Path, scale: str, data: dict) -> Report:
    """The end of an entry's run: ``data`` with the machine and the scale into out/<rep.name>.json, the report's
    tables printed; returns ``rep``."""
    write_json(out / f"{rep.name}.json", {"machine": machine(), "scale": scale, **data})
    print("\n\n".join(rep.tables))
    return rep


def fit_exponent(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope of log y against log x: cost ~ x^k."""
    lx, ly = [math.log(x) for x in xs], [math.log(y) for y in ys]
    mx, my = sum(lx) / len(lx), sum(ly) / len(ly)
    return sum((a - mx) * (b - my) for a, b in zip(lx, ly)) / sum((a - mx) ** 2 for a in lx)


def device() -> torch.device:
    """CUDA when present, else the CPU: where every entry measures."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


# ---- setups shared by several entries ---------------------------------------------------------------------------
def compose(overrides: list[str]):
    """The project's Hydra config (conf/config.yaml) with command-line style ``overrides``."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return hydra_compose("config", overrides=list(overrides))


def restorer(kind: str, size: str):
    """An untrained restoration network ``model=<kind>`` at ``model.size=<size>``, as the config builds it."""
    from codesign.config.runtime import to_container
    from codesign.models import build_restorer

    return build_restorer(to_container(compose([f"model={kind}", f"model.size={size}"]).model))


class SensorSetup(NamedTuple):
    """The default optics (conf/optics: 384 samples across, MFT) with the published half-ring mask frozen."""

    sim: object  # SensorSimulator
    state: object  # PSFState of the published mask
    key: tuple  # its cache key (mask_key=): kernels cached as in training
    mask: object  # the HalfRingMask
    system: object  # the OpticalSystem


def published_sensor(path: str = "direct", downsample: str = "area", device=None, dtype=torch.float32,
                     **sensor_kw) -> SensorSetup:
    """Simulator, PSF state, cache key, mask and system of the published mask on the default optics; ``sensor_kw``
    are further SensorSpec fields (image_size, padded_size, ...); ``dtype``: of the optics (PSF)."""
    from codesign.optics import OpticalSystem, OpticsSpec
    from codesign.optics.masks import published_halfring
    from codesign.sensor.simulator import SensorSimulator, mask_state_key, psf_state
    from codesign.sensor.spec import SensorSpec

    optics = OpticsSpec(pupil_pitch_m=3.83e-3 / 384)
    system = OpticalSystem(optics, dtype=dtype, device=device)
    mask = published_halfring(system.grid, optics.aperture_diameter_m)
    with torch.no_grad():
        state = psf_state(system, mask.phase())
    sim = SensorSimulator(SensorSpec(path=path, downsample=downsample, **sensor_kw), optics)
    return SensorSetup(sim, state, mask_state_key(mask), mask, system)


def builtin_scenes(batch: int, size: int, names: list[str] | None = None) -> torch.Tensor:
    """``batch`` built-in scenes (cycling through ``names``, default all of them) cropped to ``size``."""
    from codesign.data.scenes import build_scene_source

    src = build_scene_source({"scenes": "builtin"})
    names = names or src.split_names("all")
    return src.fixed_batch([names[i % len(names)] for i in range(batch)], size)


def fresh_model(cfg):
    """The restorer of ``cfg`` with its weights initialised as a run initialises them, from seed 0."""
    from codesign.train.model_setup import build_model
    from codesign.train.optim import init_weights

    torch.manual_seed(0)
    model = build_model(cfg)
    init_weights(model)
    return model


def bench_trainer(cfg, dev: torch.device, run_dir: Path, codesign=None, **options):
    """A Trainer of ``cfg`` as a run builds it (seed 0, fresh_model), no validation, checkpoints or images;
    ``codesign``: called with the data and the trainer spec, it returns the MaskCodesign (None: the mask stays
    frozen); ``options``: further TrainerSpec fields (amp, channels_last, compile)."""
    from codesign.config.runtime import to_container
    from codesign.train.data import build_simulated_data
    from codesign.train.model_setup import build_trainer
    from codesign.train.spec import TrainerSpec

    model = fresh_model(cfg)
    data = build_simulated_data(cfg, dev, 0)
    spec = TrainerSpec.from_config(to_container(cfg.trainer)).replace(
        steps=10**6, val_every=0, checkpoint_every=0, image_every=0, **options)
    return build_trainer(cfg, model, data, run_dir, dev, 0, spec=spec,
                         codesign=codesign(data, spec) if codesign is not None else None)


def joint_trainer(overrides: list[str], dev: torch.device, run_dir: Path, **options):
    """A co-design trainer of ``+experiment=joint`` plus ``overrides``, the mask trainable from the first step
    (codesign.warmup_fraction 0), no LSR bound in force (lsr_max 1); see bench_trainer."""
    from codesign.config.runtime import to_container
    from codesign.experiments.specs import metrics_spec
    from codesign.train.lsr_constraint import CodesignSpec
    from codesign.train.mask_codesign import MaskCodesign

    cfg = compose(["+experiment=joint", *overrides])
    cs = CodesignSpec.from_config({**(to_container(cfg.get("codesign")) or {}), "warmup_fraction": 0.0})
    return bench_trainer(cfg, dev, run_dir, lambda data, spec: MaskCodesign(
        camera=data.camera, spec=cs, lsr_max=1.0, lsr_p=metrics_spec(cfg).lsr_p, steps=spec.steps, device=dev),
        **options)


def keep_weights(src: Path, dst: Path) -> dict:
    """The trained checkpoint without its optimizer, scheduler and RNG states: what +experiment=evaluate, restore
    and init.checkpoint read, at a third of the size (the cpu-width SGAN-B: about 10 MiB, which a results folder
    and a device tool's returned files hold)."""
    from codesign.train.checkpoint import TRAINED_ENTRIES, load_checkpoint, save_checkpoint

    state = load_checkpoint(src)
    save_checkpoint(dst, {k: state[k] for k in (*TRAINED_ENTRIES, "mask") if k in state})
    return {"checkpoint": dst.name, "checkpoint_mib": round(dst.stat().st_size / 2**20, 2)}
