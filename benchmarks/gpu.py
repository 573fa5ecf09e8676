"""The GPU campaign: one command that, on a CUDA machine and within a time budget, runs in order

  1. the CUDA test subset (``pytest tests/device --device cuda``),
  2. the speed table: SGAN-B/E/F inference at 256 px padded to 384, cpu and paper widths, float32 / bf16 /
     batch 1 and 8 (images/s, peak memory); the paper-preset joint step split into its parts
     (benchmarks/bench_joint.py); the PSF chain (mask parameters -> PSF -> smooth LSR, forward + backward) at the
     default and the paper's sampling,
  3. the compiled inference cells: torch.compile (kernel fusion) and its reduce-overhead mode (CUDA graphs: one
     launch per network call; eager inference is launch-bound), float32, batch 8, SGAN-F and paper width first,
  4. a training run of the sandwich with the published mask (the rest of the budget, less the evaluation's share),
  5. its evaluation on held-out photographs (default ../shared/data/scenes) against the sensor image and classical
     Wiener at alpha_l = 0, 1e3, 1e6,

and writes gpu.json, the figures and gpu.md into benchmarks/results/gpu/ and docs/gpu.md.

    python -m benchmarks.gpu --budget-min 25                  # on the GPU node
    python -m benchmarks.gpu --dry-run --out /tmp/gpu_dry     # any CPU: every step at tiny sizes, ~1-2 min

A cell that fails (out of memory, a compile error) is recorded with its error and the campaign goes on: the
errors are the CUDA-only defects docs/results_log.md lists. A joint run warm-started from the trained network
(``+experiment=joint init.checkpoint=...``, which exists now) is not a step of the campaign yet: reported as not run.
"""
from __future__ import annotations

import argparse
import gc
import json
import math
import os
import platform
import re
import shutil
import sys
import tempfile
import time
import traceback
from pathlib import Path

import torch
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile

from benchmarks.common import compact_png, cuda_sync, gpu_driver, keep_weights, machine, markdown_table, \
    peak_cuda_mib, restorer, run_logged, timeit, write_json, write_text

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results" / "gpu"
DOCS = REPO / "docs" / "gpu.md"
SCENES = REPO.parent / "shared" / "data" / "scenes"
ALPHAS = ("0", "1e3", "1e6")
NOTES = "notes.md"  # findings written by hand beside the results; render() includes them
# how to run the campaign on an offline node, written by hand beside gpu.json: every render ends with it
RUNNING = RESULTS / "running.md"
STEPS = {"tests": "tests on the device", "speed": "speed table", "compiled": "compiled inference cells",
         "train": "training with the published mask",
         "evaluate": "evaluation on held-out scenes"}
# the dry run's physics: smoke optics, no far-PSF laser halo (seconds per mask; tests/sensor/test_laser_halo.py)
TINY_PHYSICS = ["optics.pupil_pitch_m=2.0e-5", "optics.focal_n=160", "sensor.laser_halo=false"]
PLANS = {
    "gpu": dict(models=("sgan_b", "sgan_e", "sgan_f"), widths=("cpu", "paper"), image=256, padded=384,
                batches=(1, 8), modes=("float32", "bf16"), repeats=20, joint=["preset=paper"],
                compiled=("float32+cudagraphs", "float32+compile"),  # CUDA graphs first: eager is launch-bound
                joint_warmup=2, joint_repeats=5, psf_samples=(384, 1024), psf_repeats=10,
                train=dict(model="sgan_b", size="cpu", image=256, padded=384, batch=16, amp="bf16", reserve_s=75),
                eval=[], shares=dict(tests=0.12, speed=0.2, compiled=0.15, evaluation=0.12),
                floors=dict(tests=120, speed=60, compiled=60)),
    # every step at tiny sizes on a CPU; compile is left to tests/train/test_train_options.py (a CPU compile of
    # even the tiny network takes minutes of C++ builds): the dry run's compiled step times nothing
    "dry": dict(models=("sgan_b", "sgan_f"), widths=("tiny",), image=48, padded=64, batches=(1, 2),
                modes=("float32", "bf16"), compiled=(), repeats=2, joint=["model.size=tiny", "data.image_size=48",
                "data.padded_size=64", "data.batch_size=2", *TINY_PHYSICS], joint_warmup=1, joint_repeats=1,
                psf_samples=(192,), psf_repeats=1,
                train=dict(model="sgan_b", size="tiny", image=48, padded=64, batch=2, amp=None, steps=4),
                eval=["evaluate.stages=[H1]", "evaluate.tuning_size=2", "evaluate.max_scenes=2"],
                shares=dict(tests=0.4, speed=0.3, compiled=0.0, evaluation=0.1),
                floors=dict(tests=240, speed=300, compiled=0)),
}


def portable(text: str, work: Path, out: Path) -> str:
    """``text`` (a recorded command, a folder) without this machine's paths: the campaign's temporary folder as
    <tmp>, an --out outside the checkout as <out>, the checkout's paths relative to it (tests/test_repository.py
    refuses machine paths in committed files)."""
    subs = [(str(work), "<tmp>")] + ([] if out.resolve().is_relative_to(REPO) else [(str(out), "<out>")])
    for path, name in subs + [(f"{REPO}/", ""), (str(REPO), "."), (f"{REPO.parent}/", "../")]:
        text = text.replace(path, name)
    return text


class Budget:
    """Wall-clock budget of the campaign: ``left()`` seconds remain; steps take shares of the whole."""

    def __init__(self, minutes: float):
        self.total, self.t0 = 60.0 * minutes, time.perf_counter()

    def left(self) -> float:
        return self.total - (time.perf_counter() - self.t0)

    def share(self, fraction: float, floor_s: float = 0.0) -> float:
        """``fraction`` of the whole, at least ``floor_s``, at most what is left."""
        return min(self.left(), max(fraction * self.total, floor_s))


def gpu_facts(dev: torch.device) -> dict:
    """Machine, GPU, driver and library versions."""
    info = {**machine(), "device": str(dev), "platform": platform.platform()}
    if dev.type == "cuda":
        p = torch.cuda.get_device_properties(dev)
        info.update(gpu=p.name, gpu_memory_gib=round(p.total_memory / 2**30, 1), cuda_runtime=torch.version.cuda,
                    cudnn=torch.backends.cudnn.version(), multiprocessors=p.multi_processor_count,
                    driver=gpu_driver())
    return info


def step_tests(dev: torch.device, out: Path, budget: float) -> dict:
    rc, sec = run_logged([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/device",
                          "--device", str(dev)], out / "tests.log", budget)
    tail = (out / "tests.log").read_text().strip().splitlines()
    summary = next((line for line in reversed(tail) if re.search(r"\d+ (passed|failed|error)", line)), "")
    counts = {k: int(v) for v, k in re.findall(r"(\d+) (passed|failed|skipped|errors?)", summary)}
    print(f"  tests/device on {dev}: {summary or 'no summary'} ({sec:.0f} s)", flush=True)
    return {"exit": rc, "seconds": sec, "summary": summary, **counts}


def _otf(padded: int, dev: torch.device) -> torch.Tensor:
    """OTF of a normalised 15-px Gaussian kernel: the networks' run time does not depend on the OTF's values."""
    from codesign.sensor.kernels import otf_from_kernel

    r = torch.arange(15, dtype=torch.float32) - 7
    k = torch.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / 8)
    return otf_from_kernel(k / k.sum(), padded).to(dev)


def inference_passes(p: dict, compiled: bool = False) -> list[tuple[str, str, tuple[str, ...], tuple[int, ...]]]:
    """(model, width, modes, batches) in the order they are timed: the eager cells, or the compiled ones at the
    largest batch only, SGAN-F (the paper's speed claim) and the paper width first: a torch.compile costs tens of
    seconds per network and shape, so a short budget drops the least wanted compiled cells."""
    if not compiled:
        return [(name, width, tuple(p["modes"]), tuple(p["batches"])) for name in p["models"] for width in p["widths"]]
    if not p["compiled"]:
        return []
    return [(name, width, tuple(p["compiled"]), (max(p["batches"]),))
            for name in sorted(p["models"], key=lambda n: n != "sgan_f") for width in reversed(p["widths"])]


def is_compiled(mode: str) -> bool:
    """Whether a speed-table mode compiles the networks ("float32+compile", "float32+cudagraphs")."""
    return "+" in mode


def _compiled(g, mode: str):
    """``g`` compiled for ``mode``: "+cudagraphs" is torch.compile's reduce-overhead mode (CUDA graphs replay the
    whole network in one launch), "+compile" its default (fused kernels, one launch each)."""
    if not is_compiled(mode) or getattr(g, "no_compile", False):
        return g
    return torch.compile(g, mode="reduce-overhead" if "cudagraphs" in mode else None)


def inference_cells(p: dict, dev: torch.device, budget: float, compiled: bool = False) -> list[dict]:
    """images/s and peak memory of every (model, width, mode, batch) while the budget lasts."""
    from codesign.models import parameter_count

    t_end, rows, otf = time.perf_counter() + budget, [], _otf(p["padded"], dev)
    for name, width, modes, batches in inference_passes(p, compiled):
        cells = [{"model": name, "width": width, "mode": mode, "batch": batch} for mode in modes for batch in batches]
        if time.perf_counter() > t_end:
            rows += [{**c, "error": "not run: speed budget spent"} for c in cells]
            continue
        try:
            model = restorer(name, width)
            model.check_input_size(p["padded"])
            model = model.to(dev)
        except Exception as e:  # noqa: BLE001 - recorded: a defect to list, not a reason to stop
            rows.append({"model": name, "width": width, "error": f"build: {type(e).__name__}: {e}"[:400]})
            continue
        params = sum(parameter_count(g) for g in model.generators())
        for mode in modes:
            gens = [_compiled(g, mode) for g in model.generators()]
            for batch in batches:
                row = {"model": name, "width": width, "mode": mode, "batch": batch, "params": params}
                if time.perf_counter() > t_end:
                    rows.append({**row, "error": "not run: speed budget spent"})
                    continue
                rows.append({**row, **_time_cell(model, gens, otf, p, batch, mode, dev)})
                r = rows[-1]
                said = r["error"][:120] if "error" in r else f"{r['images_per_s']:9.1f} images/s" + (
                    f", peak {r['peak_mib']:8.0f} MiB" if r["peak_mib"] else "")
                print(f"  {name} {width:5s} {mode:13s} batch {batch}: {said}", flush=True)
        model = gens = None
        if dev.type == "cuda":
            torch.cuda.empty_cache()
    return rows


def merge_compiled(old: list[dict], new: list[dict]) -> list[dict]:
    """The speed table's rows with this run's compiled cells: a cell this run measured (or failed) replaces the
    earlier one; a cell its budget did not reach keeps an earlier measurement (a short call adds cells, never
    erases them)."""
    key = lambda r: (r.get("model"), r.get("width"), r.get("mode"), r.get("batch"))  # noqa: E731
    skipped = {key(r) for r in new if r.get("error", "").startswith("not run")}
    earlier = {key(r): r for r in old if is_compiled(r.get("mode", "")) and "error" not in r}
    kept = [r for r in old if not is_compiled(r.get("mode", ""))]
    return kept + [earlier[key(r)] if key(r) in skipped and key(r) in earlier else r for r in new]


def _time_cell(model, gens, otf, p: dict, batch: int, mode: str, dev: torch.device) -> dict:
    x = torch.rand(batch, 1, p["padded"], p["padded"], device=dev)

    def call():
        with torch.no_grad(), torch.autocast(dev.type, dtype=torch.bfloat16, enabled="bf16" in mode):
            model.restore(x, otf, gens)

    try:
        peak_cuda_mib(dev, reset=True)
        sec = timeit(call, p["repeats"], warmup=3 if is_compiled(mode) else 1, sync=cuda_sync(dev))
        return {"ms_per_batch": 1e3 * sec, "images_per_s": batch / sec, "peak_mib": peak_cuda_mib(dev)}
    except Exception as e:  # noqa: BLE001 - out of memory, a compile failure: recorded, the campaign goes on
        if dev.type == "cuda":
            torch.cuda.empty_cache()
        return {"error": f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"[:400]}


def profile_cell(model, x, otf, mode: str, repeats: int = 5) -> tuple[str, str]:
    """(one summary line, the profiler's table) of ``model.restore`` on ``x`` in ``mode`` (float32 or bf16)."""
    gens = model.generators()

    def call():
        with torch.no_grad(), torch.autocast("cuda", dtype=torch.bfloat16, enabled=mode == "bf16"):
            model.restore(x, otf, gens)

    for _ in range(3):
        call()
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(repeats):
        call()
    torch.cuda.synchronize()
    wall = (time.perf_counter() - t0) / repeats
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        call()
        torch.cuda.synchronize()
    ka = prof.key_averages()
    # the device's own events (kernels, copies): an operator's row repeats its kernels' time, so summing every row
    # counts it twice (as the first campaign's prototype of this script did; docs/gpu.md uses the table's footer)
    dev_rows = [e for e in ka if e.device_type == DeviceType.CUDA and not e.is_user_annotation]
    busy_ms = sum(e.self_device_time_total for e in dev_rows) / 1e3
    launches = sum(e.count for e in dev_rows)
    line = f"wall {1e3 * wall:.1f} ms, GPU busy {busy_ms:.1f} ms, {launches} kernel calls"
    return line, ka.table(sort_by="self_device_time_total", row_limit=18, max_name_column_width=60)


def profile_inference(out: Path) -> None:
    """--profile: where SGAN-F's inference time goes (cpu and paper widths, float32 and bf16, batch 1, 256 px padded
    to 384): wall time against the GPU's busy time and kernel launches, and torch.profiler's table, in
    profile_sgan_f.txt. The first run found the forward launch-bound (docs/gpu.md, docs/results_log.md)."""
    dev, parts = torch.device("cuda"), []
    for width in ("cpu", "paper"):
        model = restorer("sgan_f", width).to(dev)
        x, otf = torch.rand(1, 1, 384, 384, device=dev), _otf(384, dev)
        for mode in ("float32", "bf16"):
            line, table = profile_cell(model, x, otf, mode)
            parts += [f"== sgan_f {width} {mode} batch 1: {line}", table]
            print(parts[-2], flush=True)
    write_text(out / "profile_sgan_f.txt", "\n".join(parts) + "\n")


def psf_chain(p: dict, dev: torch.device) -> list[dict]:
    from codesign.design.merit import time_forward_backward
    from codesign.optics import OpticalSystem, OpticsSpec
    from codesign.optics.masks import HalfRingMask

    rows = []
    for samples in p["psf_samples"]:
        spec = OpticsSpec.with_samples_across(samples)
        system = OpticalSystem(spec, device=dev)
        mask = HalfRingMask(system.grid, spec.aperture_diameter_m).to(dev)
        peak_cuda_mib(dev, reset=True)
        fwd, bwd = time_forward_backward(system, mask, 16.0, p["psf_repeats"])
        rows.append({"samples_across": samples, "grid_n": spec.grid_n, "focal_n": spec.focal_n,
                     "propagator": system.method, "forward_ms": 1e3 * fwd, "backward_ms": 1e3 * bwd,
                     "peak_mib": peak_cuda_mib(dev)})
        print(f"  PSF chain {samples} across ({system.method}): forward {1e3 * fwd:.2f} ms, backward "
              f"{1e3 * bwd:.2f} ms", flush=True)
    return rows


def step_speed(p: dict, dev: torch.device, budget: float) -> dict:
    from benchmarks.bench_joint import measure_preset

    t0 = time.perf_counter()
    out = {"inference": inference_cells(p, dev, 0.7 * budget)}
    try:
        out["joint"] = measure_preset(p["joint"], dev, p["joint_warmup"], p["joint_repeats"])
    except Exception as e:  # noqa: BLE001
        out["joint"] = {"overrides": p["joint"], "error": f"{type(e).__name__}: {e}"[:400]}
        traceback.print_exc()
    out["psf"] = psf_chain(p, dev)
    out["seconds"] = time.perf_counter() - t0
    return out


def step_train(p: dict, dev: torch.device, work: Path, out: Path, budget: float) -> dict:
    t = p["train"]
    run = work / "train"
    cmd = [sys.executable, "-m", "codesign", "+experiment=baseline", f"model={t['model']}", f"model.size={t['size']}",
           f"data.image_size={t['image']}", f"data.padded_size={t['padded']}", f"data.batch_size={t['batch']}",
           f"device={dev}", "trainer.first_fraction=1.0", "trainer.image_every=0", f"hydra.run.dir={run}"]
    if "steps" in t:  # dry run: a fixed number of steps
        cmd += [f"trainer.steps={t['steps']}", "trainer.val_every=2", "trainer.checkpoint_every=2",
                "evaluate.stages=[H1]", "evaluate.tuning_size=2", "evaluate.max_scenes=2", *TINY_PHYSICS]
    else:  # as many steps as the budget holds at a constant learning rate (the schedule would need the count)
        train_s = max(budget - t["reserve_s"], 60)  # start-up, the run's own short evaluation, the checkpoint
        cmd += ["trainer.steps=10000000", f"trainer.time_budget_s={train_s:.0f}", "trainer.val_every=500",
                "trainer.checkpoint_every=2000", "evaluate.stages=[H1]", "evaluate.max_scenes=2"]
    if t.get("amp"):
        cmd += [f"trainer.amp={t['amp']}", "trainer.channels_last=true"]
    print(f"  training: {' '.join(cmd[2:])}", flush=True)
    rc, sec = run_logged(cmd, out / "train.log", budget + 300)
    metrics = json.loads((run / "metrics.json").read_text()) if (run / "metrics.json").is_file() else {}
    keep = ("variant", "size", "parameters_generators", "parameters_critics", "steps", "seconds", "image_size",
            "padded_size", "skipped_updates")
    res = {"exit": rc, "wall_seconds": sec, "command": portable("python -m " + " ".join(cmd[2:]), work, out),
           **{k: metrics[k] for k in keep if k in metrics}}
    if (run / "checkpoint.pt").is_file():
        res.update(keep_weights(run / "checkpoint.pt", out / "checkpoint.pt"))
    print(f"  training: exit {rc}, {res.get('steps', '?')} steps in {sec:.0f} s", flush=True)
    return res


def step_evaluate(p: dict, dev: torch.device, checkpoint: str, scenes: Path | None, work: Path, out: Path,
                  budget: float) -> dict:
    run = work / "evaluate"
    source = ["data.scenes=folder", f"data.folder={scenes}", "evaluate.scenes=data", "evaluate.split=all",
              "evaluate.max_scenes=12"] if scenes else ["evaluate.scenes=heldout"]
    cmd = [sys.executable, "-m", "codesign", "+experiment=evaluate", f"checkpoint={checkpoint}", f"device={dev}",
           "evaluate.laser_strengths=[0,1e3,1e6]", *source, *p["eval"], f"hydra.run.dir={run}"]
    rc, sec = run_logged(cmd, out / "evaluate.log", budget + 120)
    m = json.loads((run / "metrics.json").read_text()) if (run / "metrics.json").is_file() else {}
    scores = {meth: {a: {q: m.get(f"{q}_{meth}_laser_{a}") for q in ("psnr", "ssim", "psnr_matched")}
                     for a in ALPHAS} for meth in ("sgan", "sensor", "wiener")}
    panel = run / "panel_laser_1e6.png"
    if panel.is_file():
        shutil.copyfile(panel, out / "restorations_1e6.png")
    print(f"  evaluation: exit {rc}, {sec:.0f} s", flush=True)
    return {"exit": rc, "seconds": sec, "scenes": portable(str(scenes), work, out) if scenes else "built-in test split",
            "evaluation_scenes": m.get("evaluation_scenes"), "scores": scores,
            "command": portable("python -m " + " ".join(cmd[2:]), work, out)}


def inference_figure(rows: list[dict], path: Path) -> Path | None:
    from codesign.io.files import save_figure
    from codesign.io.plots import plt

    ok = [r for r in rows if "error" not in r]
    if not ok:
        return None
    top = max(r["batch"] for r in ok)
    ok = [r for r in ok if r["batch"] == top]
    labels = sorted({f"{r['model']} {r['width']}" for r in ok})
    modes = sorted({r["mode"] for r in ok})
    fig, ax = plt.subplots(figsize=(7, 4))
    w = 0.8 / len(modes)
    for j, mode in enumerate(modes):
        vals = [next((r["images_per_s"] for r in ok if f"{r['model']} {r['width']}" == lab and r["mode"] == mode),
                     0.0) for lab in labels]
        ax.bar([i + j * w for i in range(len(labels))], vals, w, label=mode)
    ax.axhline(25, color="0.4", ls=":", label="paper: 25 FPS")
    ax.set(xticks=[i + 0.4 - w / 2 for i in range(len(labels))], ylabel="images / s", yscale="log",
           title=f"restoration throughput, batch {top}")
    ax.set_xticklabels(labels, rotation=20, fontsize=7)
    ax.legend(fontsize=7)
    return compact_png(save_figure(path, fig))


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.gpu", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--budget-min", type=float, default=25.0, help="wall-clock budget in minutes (default 25)")
    ap.add_argument("--dry-run", action="store_true", help="every step at tiny sizes, on the CPU unless --device")
    ap.add_argument("--device", default=None, help="cuda, cuda:N or cpu (default: cuda; cpu for --dry-run)")
    ap.add_argument("--out", type=Path, default=None,
                    help=f"results folder (default {RESULTS.relative_to(REPO)}; a dry run needs its own)")
    ap.add_argument("--scenes", type=Path, default=None,
                    help="held-out photographs (default ../shared/data/scenes; a dry run without it: built-in test)")
    ap.add_argument("--only", default=None, help=f"comma-separated steps of {', '.join(STEPS)} (default all); the "
                    "results of the others in --out's gpu.json are kept (a device allowing 10 minutes per command "
                    "runs the campaign in two calls)")
    ap.add_argument("--checkpoint", type=Path, default=None, help="for --only evaluate: the trained checkpoint")
    ap.add_argument("--profile", action="store_true", help="run only the inference profile (CUDA): "
                    "profile_sgan_f.txt in --out")
    ap.add_argument("--render", action="store_true", help="run nothing: write gpu.md (and docs/gpu.md for GPU "
                    "results) again from --out's gpu.json, e.g. results a device run wrote elsewhere, copied here")
    return ap


def _steps_and_device(ap: argparse.ArgumentParser, a: argparse.Namespace) -> tuple[list[str], torch.device]:
    """The steps to run, in the campaign's order, and the device: every argument checked before any work."""
    steps = [s.strip() for s in (a.only or ",".join(STEPS)).split(",") if s.strip()]
    if not steps or any(s not in STEPS for s in steps):
        ap.error(f"--only {a.only!r}: allowed steps: {', '.join(STEPS)} (comma-separated)")
    if a.checkpoint is not None and not a.checkpoint.is_file():
        ap.error(f"--checkpoint {a.checkpoint}: no such file")
    if not 1 <= a.budget_min <= 600:
        ap.error(f"--budget-min {a.budget_min:g}: must be between 1 and 600")
    return [s for s in STEPS if s in steps], torch.device(a.device or ("cpu" if a.dry_run else "cuda"))


def _scenes(ap: argparse.ArgumentParser, a: argparse.Namespace, dev: torch.device) -> Path | None:
    """The held-out photographs (None: the built-in test split, a dry run's fallback), after the checks that a GPU
    run needs (a CUDA device, its own results folder for a dry run)."""
    if dev.type == "cuda" and not torch.cuda.is_available():
        ap.error(f"no CUDA device visible (torch {torch.__version__}): run on a GPU node, or --dry-run on a CPU")
    if a.dry_run and a.out is None:
        ap.error("--dry-run needs --out DIR (its tiny-size figures must not replace the GPU results)")
    if not a.dry_run and dev.type != "cuda":
        ap.error(f"--device {dev}: the campaign measures a GPU; --dry-run for a CPU rehearsal")
    scenes = a.scenes or (SCENES if SCENES.is_dir() else None)
    if scenes is not None and not scenes.is_dir():
        ap.error(f"--scenes {scenes}: no such folder")
    if scenes is None and not a.dry_run:
        ap.error(f"no held-out scenes: {SCENES} is missing; give --scenes DIR (the 12 photographs)")
    return scenes


def main(argv=None) -> int:
    ap = _parser()
    a = ap.parse_args(argv)
    if a.render:
        out = a.out or RESULTS
        if not (out / "gpu.json").is_file():
            ap.error(f"--render: {out / 'gpu.json'} does not exist")
        res = json.loads((out / "gpu.json").read_text())
        publish(res, out, res["dry_run"])
        print(f"rendered {out / 'gpu.md'}" + ("" if res["dry_run"] else f" and {DOCS}"))
        return 0
    steps, dev = _steps_and_device(ap, a)
    if a.profile and not a.dry_run:
        if not torch.cuda.is_available():
            ap.error(f"--profile: no CUDA device visible (torch {torch.__version__}): it profiles the GPU")
        (a.out or RESULTS).mkdir(parents=True, exist_ok=True)
        profile_inference(a.out or RESULTS)
        return 0
    scenes = _scenes(ap, a, dev)
    out = a.out or RESULTS
    out.mkdir(parents=True, exist_ok=True)
    earlier = json.loads((out / "gpu.json").read_text()) if (out / "gpu.json").is_file() and \
        steps != list(STEPS) else {}
    if earlier and earlier.get("dry_run") != a.dry_run:
        ap.error(f"{out / 'gpu.json'} holds a {'dry' if earlier.get('dry_run') else 'GPU'} run: a partial run "
                 "(--only) adds to results of its own kind only")
    res = campaign(a, steps, dev, scenes, out, earlier)
    print(f"done in {sum(res['seconds'][s] for s in steps) / 60:.1f} min: {out / 'gpu.json'}"
          + ("" if a.dry_run else f", {DOCS}"))
    ran = [{"evaluate": "evaluation"}.get(s, s) for s in steps if s not in ("speed", "compiled")]
    return 1 if any(res[k].get("exit") != 0 for k in ran) else 0


def campaign(a: argparse.Namespace, steps: list[str], dev: torch.device, scenes: Path | None, out: Path,
             earlier: dict) -> dict:
    """Run ``steps`` in order, each with its share of the budget, into ``out`` (``earlier``: the results of the
    steps a partial run keeps); gpu.json and the pages are written after every step."""
    p, budget = PLANS["dry" if a.dry_run else "gpu"], Budget(a.budget_min)
    facts = gpu_facts(dev)
    print(f"GPU campaign{' (dry run)' if a.dry_run else ''} on {facts.get('gpu', dev)}, steps {', '.join(steps)}, "
          f"budget {a.budget_min:g} min, results in {out}", flush=True)
    res = {**earlier, "dry_run": a.dry_run, "plan": p,
           "machines": {**earlier.get("machines", {}), **{s: facts for s in steps}}}
    with tempfile.TemporaryDirectory(prefix="codesign_gpu_") as tmp:
        work = Path(tmp)
        for i, step in enumerate(steps, 1):
            print(f"[{i}/{len(steps)}] {STEPS[step]}", flush=True)
            t0 = time.perf_counter()
            if step == "tests":
                res["tests"] = step_tests(dev, out, budget.share(p["shares"]["tests"], p["floors"]["tests"]))
            elif step == "speed":
                res["speed"] = step_speed(p, dev, budget.share(p["shares"]["speed"], p["floors"]["speed"]))
                if dev.type == "cuda":  # the paper-width cells' cached blocks: the training process needs them
                    gc.collect()
                    torch.cuda.empty_cache()
            elif step == "compiled":
                speed = res.setdefault("speed", {"inference": []})
                speed["inference"] = merge_compiled(speed["inference"], inference_cells(
                    p, dev, budget.share(p["shares"]["compiled"], p["floors"]["compiled"]), compiled=True))
            elif step == "train":
                reserve = p["shares"]["evaluation"] * budget.total if "evaluate" in steps else 0.0
                res["train"] = step_train(p, dev, work, out, budget.left() - reserve)
            else:
                ckpt = a.checkpoint or out / res.get("train", {}).get("checkpoint", "checkpoint.pt")
                res["evaluation"] = step_evaluate(p, dev, str(ckpt), scenes, work, out, max(budget.left(), 60)) \
                    if ckpt.is_file() else {"exit": None, "error": f"no checkpoint ({ckpt}): the training failed "
                                                                   "or was not run (train.log; --checkpoint PATH)"}
            res.setdefault("seconds", {})[step] = time.perf_counter() - t0
            publish(res, out, a.dry_run)  # after every step: a campaign cut short keeps what it measured
    return res


def publish(res: dict, out: Path, dry_run: bool) -> None:
    """gpu.json, the throughput figure and gpu.md in ``out``; docs/gpu.md too for a GPU run."""
    res.setdefault("joint_from_trained", "not run: the campaign has no warm-started joint step yet (init.checkpoint "
                   "exists: python -m codesign +experiment=joint init.checkpoint=CKPT, same sizes)")
    write_json(out / "gpu.json", res)
    fig = inference_figure(res["speed"]["inference"], out / "inference.png") if "speed" in res else None
    write_text(out / "gpu.md", render(res, out, fig, ""))
    if not dry_run:
        write_text(DOCS, render(res, out, fig, os.path.relpath(out, DOCS.parent) + "/"))


def _fmt(v, spec=".2f") -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def _machine_line(m: dict) -> str:
    gpu = (f"{m['gpu']} ({m.get('gpu_memory_gib')} GiB), driver {m.get('driver')}, CUDA runtime "
           f"{m.get('cuda_runtime')}, cuDNN {m.get('cudnn')}" if m.get("gpu") else m["device"])
    return f"{gpu}; {m['cpu']}, {m['cores']} cores; torch {m['torch']}, Python {m['python']}; {m['date']}"


def _speed_lines(res: dict, sp: dict, fig: Path | None, prefix: str) -> list[str]:
    from benchmarks.bench_joint import PARTS

    plan = res["plan"]
    lines = [f"Restoration inference ({plan['image']} px images padded to {plan['padded']}, no gradient, median "
             f"of {plan['repeats']} calls; a compiled cell (+compile: torch.compile, +cudagraphs: its reduce-overhead "
             "mode) after 3 warm-up calls):", ""]
    rows = [[r["model"], r["width"], r.get("mode", "-"), r.get("batch", "-"), r.get("params", "-"),
             _fmt(r.get("images_per_s"), ".1f"), _fmt(r.get("ms_per_batch"), ".2f"), _fmt(r.get("peak_mib"), ".0f"),
             r.get("error", "")] for r in sp["inference"]]
    lines += [markdown_table(["model", "width", "mode", "batch", "params", "images/s", "ms/batch", "peak MiB",
                              "error"], rows), ""]
    f_rows = [r for r in sp["inference"] if r["model"] == "sgan_f" and "images_per_s" in r]
    if f_rows:
        best = max(f_rows, key=lambda r: r["images_per_s"])
        lines += [f"SGAN-F best: {best['images_per_s']:.1f} images/s ({best['width']} width, {best['mode']}, batch "
                  f"{best['batch']}), {best['images_per_s'] / 25:.1f}x the paper's 25 FPS (goal: >= 100).", ""]
    if fig:
        lines += [f"![inference]({prefix}{fig.name})", ""]
    j = sp.get("joint", {"overrides": [], "error": "not run (the speed step was not run)"})
    if "joint" in j:
        optics = sum(j["joint"].get(k, 0.0) for k in ("mask_to_psf", "psf_to_kernel_otf", "simulation"))
        lines += [f"Joint step (`+experiment=joint {' '.join(j['overrides'])}`: {j['model_size']}-width {j['model']}, "
                  f"{j['image_size']} px padded to {j['padded_size']}, batch {j['batch_size']}; goal <= 0.5 s): "
                  f"{j['joint']['total']:.3f} s, the optics {optics / j['joint']['total']:.0%} of it:", "",
                  markdown_table(["part", "joint step [s]", "frozen-mask step [s]"],
                                 [[n, _fmt(j["joint"].get(k), ".4f"), _fmt(j["frozen"].get(k), ".4f")]
                                  for k, n in PARTS] + [["**step**", _fmt(j["joint"]["total"], ".4f"),
                                                         _fmt(j["frozen"]["total"], ".4f")]]), ""]
    else:
        lines += [f"Joint step (`{' '.join(j['overrides'])}`): {j.get('error')}", ""]
    lines += ["PSF chain (mask parameters -> half-ring phase -> PSF -> smooth LSR), float32:", "",
              markdown_table(["samples across", "grid", "window", "propagator", "forward ms", "backward ms",
                              "peak MiB"], [[r["samples_across"], r["grid_n"], r["focal_n"], r["propagator"],
                                             _fmt(r["forward_ms"]), _fmt(r["backward_ms"]), _fmt(r["peak_mib"], ".0f")]
                                            for r in sp.get("psf", [])]), ""]
    return lines


def _evaluation_lines(e: dict, out: Path, prefix: str) -> list[str]:
    if e.get("exit") is None:
        return [e["error"], ""]
    names = e.get("evaluation_scenes") or []
    lines = [f"{len(names)} scenes ({e['scenes']}: {', '.join(map(str, names))}), `{e['command']}`, exit "
             f"{e['exit']}: PSNR / SSIM / PSNR matched (after a per-image gain/offset match)", ""]
    rows = [[meth] + [" / ".join([_fmt(e["scores"][meth][a]["psnr"]), _fmt(e["scores"][meth][a]["ssim"], ".3f"),
                                  _fmt(e["scores"][meth][a]["psnr_matched"])]) for a in ALPHAS]
            for meth in ("sgan", "sensor", "wiener")]
    lines += [markdown_table(["method"] + [f"alpha_l = {a}" for a in ALPHAS], rows), ""]
    if (out / "restorations_1e6.png").is_file():
        lines += [f"![restorations at alpha_l = 1e6]({prefix}restorations_1e6.png)", ""]
    return lines


def render(res: dict, out: Path, fig: Path | None, prefix: str) -> str:
    """gpu.md; figures linked as ``prefix`` + their name in ``out``. A step not run yet says so."""
    head = "GPU campaign" + (" (DRY RUN on a CPU at tiny sizes: not GPU figures)" if res["dry_run"] else "")
    machines = res.get("machines", {})
    lines = [f"# {head}", "",
             "Sections 1-4 are generated by `python -m benchmarks.gpu"
             + (" --dry-run" if res["dry_run"] else "") + f"` from gpu.json; do not edit them by hand. Any section "
             f"between them is written by hand in {NOTES} beside gpu.json (benchmarks/results/gpu/ for docs/gpu.md) "
             "and copied in by every render: edit it there. How to set up an offline GPU node and run it: *Running "
             f"it* at the end (by hand too: benchmarks/results/gpu/{RUNNING.name}). Steps and their wall time: "
             + ", ".join(f"{k} {v / 60:.1f} min" for k, v in res.get("seconds", {}).items()) + ".", ""]
    for (key, title), body in (
            (("tests", "1. Tests on the device"), lambda r: [
                f"`pytest tests/device --device {machines.get('tests', {}).get('device', '?')}`: "
                f"{r['summary'] or 'no summary'} "
                f"(exit {r['exit']}, {r['seconds']:.0f} s; log `tests.log`).", ""]),
            (("speed", "2. Speed"), lambda r: _speed_lines(res, r, fig, prefix)),
            (("train", "3. Training with the published mask"), lambda r: [
                f"`{r['command']}`: exit {r['exit']}, {r.get('steps', '?')} steps, {r['wall_seconds']:.0f} s wall "
                f"({r.get('parameters_generators', '?')} generator parameters); log `train.log`; checkpoint "
                f"`{r['checkpoint']}`.", ""]),
            (("evaluation", "4. Held-out evaluation"), lambda r: _evaluation_lines(r, out, prefix))):
        step = "evaluate" if key == "evaluation" else key
        lines += [f"## {title}", ""]
        if key not in res:
            lines += ["Not run yet.", ""]
            continue
        lines += [f"*{_machine_line(machines[step])}*" if step in machines else "", ""] + body(res[key])
    lines += [f"Joint run from the trained network: {res['joint_from_trained']}.", ""]
    if (out / NOTES).is_file():  # what a person read in the figures: kept across re-renders
        lines += [(out / NOTES).read_text().strip(), ""]
    return "\n".join(lines + [RUNNING.read_text()])


if __name__ == "__main__":
    sys.exit(main())
