"""The training path's options (trainer.amp, channels_last, compile): joint step time, SGAN-F inference FPS, memory.

For each option set a fresh co-design trainer (+experiment=joint, mask trainable from the first step) runs warm-up
steps (the first, which pays torch.compile's compilation, is reported apart), then the median of timed steps.
SGAN-F inference: batch 1 at data.image_size 256 padded to 384 (the paper's geometry; paper width on a GPU,
the cpu width on a CPU), frames per second with and without bf16 autocast (and torch.compile at full scale). On a
GPU every timing synchronizes before reading the clock, and the peak allocated memory is recorded. The joint step
is the +experiment=joint CPU preset on a CPU (cpu width, 96 px padded to 128, batch 4) and the paper's sizes on a
GPU (paper width, 256 px padded to 384, batch 8).

Quick scale: no torch.compile rows (compiling takes minutes on a CPU), 3 timed steps, 3 timed inference calls;
full scale: every option, 10 timed steps, 20 timed inference calls (docs/scaling.md quotes these).

    python -m benchmarks --only train_options [--scale full]
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from benchmarks.common import (Report, bench_trainer, compose, cuda_sync, device, finish, joint_trainer,
                               markdown_table, peak_cuda_mib, timeit)

OPTIONS = {  # name -> trainer overrides
    "float32": {}, "bf16": {"amp": "bf16"}, "channels_last": {"channels_last": True},
    "bf16 + channels_last": {"amp": "bf16", "channels_last": True}, "compile": {"compile": True},
    "bf16 + compile": {"amp": "bf16", "compile": True},
}
PLAN = {"quick": dict(compile=False, steps=3, repeats=3, recipe_steps=12),
        "full": dict(compile=True, steps=10, repeats=20, recipe_steps=40)}
# the paper's sizes on a GPU; on a CPU the joint_cpu preset of +experiment=joint (cpu width, 96 px padded to 128)
GPU_SIZE = ["model.size=paper", "data.image_size=256", "data.padded_size=384", "data.batch_size=8"]


def joint_step(dev: torch.device, options: dict, steps: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        tr = joint_trainer(GPU_SIZE if dev.type == "cuda" else [], dev, Path(tmp), **options)
        cfg = OmegaConf.create(tr.config)
        sync = cuda_sync(dev)
        peak_cuda_mib(dev, reset=True)
        t0 = time.perf_counter()
        tr.train_step()
        if sync:
            sync()
        first = time.perf_counter() - t0
        per_step = timeit(tr.train_step, steps, warmup=2, sync=sync)
    return {"first_step_s": first, "step_s": per_step, "peak_mib": peak_cuda_mib(dev),
            "batch": int(cfg.data.batch_size), "size": str(cfg.model.size), "padded": int(cfg.data.padded_size)}


def restorer_trainer(overrides: list[str], dev: torch.device, run_dir: Path, model: str = "sgan_b_gated"):
    """A restorer stage at the main job's sizes and CPU schedule (``model``: the gated network these timings were
    first taken of; the main job's is sgan_b_l1) as a plain trainer: the published mask frozen (bench_trainer)."""
    cfg = compose(["+experiment=baseline", f"model={model}", "preset=joint_cpu", "trainer=joint_cpu",
                   f"device={dev.type}", *overrides])
    return bench_trainer(cfg, dev, run_dir)


def step_parts(dev: torch.device, steps: int) -> dict:
    """Where a restorer step's time goes (the main job's network, mask frozen), each part timed alone on the same
    batch (median of ``steps``): the batch's simulation, the generators' forward pass with its graph, one critic
    update (on that pass's outputs), one generator update (forward, losses, backward, guarded Adam step, EMA), and
    the whole step."""
    with tempfile.TemporaryDirectory() as tmp:
        tr = restorer_trainer(GPU_SIZE if dev.type == "cuda" else [], dev, Path(tmp))
        u, sync = tr.update, cuda_sync(dev)
        batch = tr.data.train_batch(0)
        tr.model.train()

        parts = {"simulation": lambda: tr.data.train_batch(1), "generators forward": lambda: u.generate(batch),
                 # the critic terms detach the outputs they are given
                 "critic update + forward": lambda: u.critic_update(batch, u.generate(batch)),
                 "generator update": lambda: u.generator_update(batch), "whole step": tr.train_step}
        times = {k: timeit(fn, steps, warmup=2, sync=sync) for k, fn in parts.items()}
    times["critic update"] = times.pop("critic update + forward") - times["generators forward"]
    return {k: times[k] for k in ("simulation", "generators forward", "critic update", "generator update",
                                  "whole step")}


# docs/models.md Sec. 13's recipe, the main job's: model=sgan_b_l1 (G2 ungated, held to the exposure, its L1 terms
# only) on log-spaced lasers
L1_RECIPE = ("sgan_b_l1", ["data.params.alpha_l_spacing=log"])


def recipe_steps(dev: torch.device, steps: int) -> dict:
    """Whole restorer steps of the main job's recipe and of the L1 recipe, the latter also with G1 run on every image
    (its skip of the images without a saturated pixel off): the mean of ``steps`` consecutive steps after 2 warm-up
    steps (each step its own batch, so the share of unlasered images varies as in training; every variant sees the
    same batches), and that share."""
    from codesign.models import sandwich
    from codesign.models.fill import saturated_fraction

    def run(model: str, overrides: list[str]) -> dict:
        with tempfile.TemporaryDirectory() as tmp:
            tr = restorer_trainer(overrides + (GPU_SIZE if dev.type == "cuda" else []), dev, Path(tmp), model)
            for _ in range(2):
                tr.train_step()
            skipped = sum(int((saturated_fraction(tr.data.train_batch(tr.step + k)["sensor"]) == 0).sum())
                          for k in range(steps))
            sync = cuda_sync(dev)
            if sync:
                sync()
            t0 = time.perf_counter()
            for _ in range(steps):
                tr.train_step()
            if sync:
                sync()
            return {"step_s": (time.perf_counter() - t0) / steps,
                    "unlasered_share": skipped / (steps * tr.data.sampler.batch_size)}

    out = {"main job's recipe": run("sgan_b_gated", []), "L1 recipe": run(*L1_RECIPE)}
    skip = sandwich.gated_correction
    sandwich.gated_correction = lambda g1, inputs, gate: g1(inputs) * gate[:, None, None, None]
    try:
        out["L1 recipe, G1 on every image"] = run(*L1_RECIPE)
    finally:
        sandwich.gated_correction = skip
    return out


def inference_fps(dev: torch.device, amp: bool, compiled: bool, repeats: int) -> dict:
    from codesign.train.model_setup import build_model

    size = "paper" if dev.type == "cuda" else "cpu"
    cfg = compose(["+experiment=baseline", "model=sgan_f", f"model.size={size}", "data.image_size=256",
                   "data.padded_size=384"])
    model = build_model(cfg).to(dev).eval()
    p = int(cfg.data.padded_size)
    sensor = torch.rand(1, 1, p, p, device=dev)
    otf = torch.ones(p, p // 2 + 1, dtype=torch.complex64, device=dev)
    run = torch.compile(model) if compiled else model

    @torch.no_grad()
    def once():
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=amp):
            run(sensor, otf)

    peak_cuda_mib(dev, reset=True)
    t0 = time.perf_counter()
    once()
    first = time.perf_counter() - t0
    s = timeit(once, repeats, warmup=2, sync=cuda_sync(dev))
    return {"fps": 1.0 / s, "ms": s * 1e3, "first_call_s": first, "peak_mib": peak_cuda_mib(dev), "size": size}


def measure(scale: str) -> dict:
    p = PLAN[scale]
    dev = device()
    names = [n for n in OPTIONS if p["compile"] or "compile" not in n]
    joint = {}
    for n in names:
        joint[n] = joint_step(dev, OPTIONS[n], p["steps"])
        print(f"  joint step {n}: {joint[n]['step_s'] * 1e3:.0f} ms (first step {joint[n]['first_step_s']:.1f} s)",
              flush=True)
    parts = step_parts(dev, p["steps"])
    print("  restorer step: " + ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in parts.items()), flush=True)
    recipes = recipe_steps(dev, p["recipe_steps"])
    print("  restorer step by recipe: " + ", ".join(f"{k} {v['step_s'] * 1e3:.0f} ms" for k, v in recipes.items()),
          flush=True)
    infer = {}
    for amp in (False, True):
        for compiled in ((False, True) if p["compile"] else (False,)):
            key = ("bf16" if amp else "float32") + (" + compile" if compiled else "")
            infer[key] = inference_fps(dev, amp, compiled, p["repeats"])
            print(f"  SGAN-F inference {key}: {infer[key]['fps']:.2f} FPS", flush=True)
    return {"device": str(dev), "steps": p["steps"], "repeats": p["repeats"], "joint_step": joint,
            "restorer_step_parts": parts, "restorer_step_recipes": recipes, "recipe_steps": p["recipe_steps"],
            "sgan_f_inference_256": infer}


def report(data: dict) -> Report:
    joint, infer = data["joint_step"], data["sgan_f_inference_256"]
    base = joint["float32"]["step_s"]
    rows = [[n, r["size"], r["batch"], r["padded"], r["step_s"] * 1e3, base / r["step_s"], r["first_step_s"],
             r["peak_mib"] if r["peak_mib"] is not None else "-"] for n, r in joint.items()]
    t_joint = markdown_table(["option", "width", "batch", "padded", "ms/step", "speed-up", "first step s",
                              "peak MiB"], rows,
                             {"ms/step": ".0f", "speed-up": ".2f", "first step s": ".1f", "peak MiB": ".0f"})
    parts = data.get("restorer_step_parts", {})
    t_parts = markdown_table(["restorer step (main job's network, mask frozen)", "ms", "share of the step"],
                             [[k, v * 1e3, v / parts["whole step"]] for k, v in parts.items()],
                             {"ms": ".0f", "share of the step": ".0%"}) if parts else ""
    recipes = data.get("restorer_step_recipes", {})
    first = next(iter(recipes.values()), None)
    t_recipes = markdown_table(["restorer step by recipe", "ms/step", "speed-up", "images without a laser"],
                               [[k, r["step_s"] * 1e3, first["step_s"] / r["step_s"], r["unlasered_share"]]
                                for k, r in recipes.items()],
                               {"ms/step": ".0f", "speed-up": ".2f", "images without a laser": ".0%"}) \
        if recipes else ""
    fbase = infer["float32"]["fps"]
    rows = [[k, r["size"], r["fps"], r["fps"] / fbase, r["first_call_s"], r["peak_mib"] if r["peak_mib"] is not None
             else "-"] for k, r in infer.items()]
    t_infer = markdown_table(["SGAN-F inference (256 px padded to 384, batch 1)", "width", "FPS", "speed-up",
                              "first call s", "peak MiB"], rows,
                             {"FPS": ".2f", "speed-up": ".2f", "first call s": ".1f", "peak MiB": ".0f"})
    notes = [
        f"Joint step: `+experiment=joint` with the mask trainable from the first step, one fresh trainer per option "
        f"(`trainer.amp=bf16`, `trainer.channels_last=true`, `trainer.compile=true`), median of {data['steps']} "
        f"steps after 2 warm-up steps on {data['device']}; 'first step' is the first step apart (it pays "
        "torch.compile's compilation). SGAN-F inference: eval mode, no gradient, median of "
        f"{data['repeats']} calls after 2 warm-up calls, with and without bf16 autocast"
        + (" and torch.compile." if any("compile" in k for k in infer) else
           "; the torch.compile rows are measured at full scale only (compiling takes minutes on a CPU)."),
    ]
    notes.append("Restorer step: the parts timed one by one on one batch (median of the same step count): the "
                 "simulation of the next batch, the generators' forward pass with its graph, one critic update "
                 "(WGAN terms and gradient penalty of D1 and both D2 scales), one generator update (forward, losses "
                 "with the frozen critics, backward, guarded Adam step, EMA); the whole step holds one of each.")
    if recipes:
        notes.append(f"Restorer step by recipe: the whole step of the main job's network, the mean of "
                     f"{data['recipe_steps']} consecutive steps (their own batches) after 2 warm-up steps; the L1 "
                     "recipe is docs/models.md Sec. 13's (no critic update); 'G1 on every image' turns off its skip "
                     "of the images without a saturated pixel (their G1 correction is exactly 0).")
    tables = [t_joint] + [t for t in (t_parts, t_recipes) if t] + [t_infer]
    return Report("train_options", "Training options: bf16, channels-last, torch.compile", tables, [],
                  notes)


def run(scale: str, out: Path) -> Report:
    data = measure(scale)
    return finish(report(data), out, scale, data)


if __name__ == "__main__":
    from benchmarks.__main__ import standalone

    standalone(run)
