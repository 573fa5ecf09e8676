"""The training path's options (trainer.amp, channels_last, compile): joint step time, SGAN-F inference FPS, memory.

For each option set a fresh co-design trainer (+experiment=joint, mask trainable from the first step) runs warm-up
steps (the first, which pays torch.compile's compilation, is reported apart), then the median of timed steps.
SGAN-F inference: batch 1 at data.image_size 256 padded to 384 (the paper's geometry; paper width on a GPU,
the cpu width on a CPU), frames per second with and without bf16 autocast and torch.compile. On a GPU every
timing synchronizes before reading the clock, and the peak allocated memory is recorded.

    python -m benchmarks.bench_train_options [--device auto|cpu|cuda] [--steps 10] [--no-compile]

Writes benchmarks/results/train_options_<device>.json and prints the tables (docs/scaling.md quotes them).
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from benchmarks.common import cuda_sync, machine, markdown_table, peak_cuda_mib, timeit, write_json

CONF = Path(__file__).resolve().parent.parent / "conf"
RESULTS = Path(__file__).resolve().parent / "results"
OPTIONS = {  # name -> trainer overrides
    "float32": {}, "bf16": {"amp": "bf16"}, "channels_last": {"channels_last": True},
    "bf16 + channels_last": {"amp": "bf16", "channels_last": True}, "compile": {"compile": True},
    "bf16 + compile": {"amp": "bf16", "compile": True},
}


def _joint_cfg(dev: torch.device):
    from hydra import compose, initialize_config_dir

    size = ["model.size=paper", "data.image_size=256", "data.padded_size=384", "data.batch_size=8"] \
        if dev.type == "cuda" else []  # CPU: the joint_cpu preset (cpu width, 96 px padded to 128, batch 4)
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=["+experiment=joint", *size])


def joint_step(dev: torch.device, options: dict, steps: int) -> dict:
    from codesign.config.runtime import to_container
    from codesign.design.lsr_constraint import CodesignSpec
    from codesign.train.data import SimulatedData
    from codesign.train.joint_trainer import JointTrainer
    from codesign.train.setup import build_model
    from codesign.train.spec import TrainerSpec
    from codesign.train.trainer import init_weights

    cfg = _joint_cfg(dev)
    torch.manual_seed(0)
    model = build_model(cfg)
    init_weights(model)
    data = SimulatedData(cfg, dev, 0)
    spec = TrainerSpec.from_config(to_container(cfg.trainer)).replace(steps=10**6, val_every=0, checkpoint_every=0,
                                                                    image_every=0, **options)
    cs = CodesignSpec.from_config({**to_container(cfg.codesign), "warmup_fraction": 0.0})
    tr = JointTrainer(model, data, spec, Path(tempfile.mkdtemp()), dev, {}, None, 0, cs, 1.0)
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


def inference_fps(dev: torch.device, amp: bool, compiled: bool, repeats: int) -> dict:
    from hydra import compose, initialize_config_dir

    from codesign.train.setup import build_model

    size = "paper" if dev.type == "cuda" else "cpu"
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=["+experiment=baseline", "model=sgan_f", f"model.size={size}",
                                           "data.image_size=256", "data.padded_size=384"])
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


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_train_options")
    ap.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    ap.add_argument("--steps", type=int, default=10, help="timed joint steps per option (median)")
    ap.add_argument("--repeats", type=int, default=20, help="timed inference calls (median)")
    ap.add_argument("--no-compile", action="store_true", help="skip the torch.compile rows (minutes on a CPU)")
    a = ap.parse_args(argv)
    dev = torch.device("cuda" if a.device == "auto" and torch.cuda.is_available() else
                       ("cpu" if a.device == "auto" else a.device))
    names = [n for n in OPTIONS if not (a.no_compile and "compile" in n)]
    joint = {}
    for n in names:
        joint[n] = joint_step(dev, OPTIONS[n], a.steps)
        print(f"joint step {n}: {joint[n]['step_s'] * 1e3:.0f} ms (first step {joint[n]['first_step_s']:.1f} s)",
              flush=True)
    infer = {}
    for amp in (False, True):
        for compiled in ((False,) if a.no_compile else (False, True)):
            key = ("bf16" if amp else "float32") + (" + compile" if compiled else "")
            infer[key] = inference_fps(dev, amp, compiled, a.repeats)
            print(f"SGAN-F inference {key}: {infer[key]['fps']:.2f} FPS", flush=True)
    base = joint["float32"]["step_s"]
    rows = [[n, r["size"], r["batch"], r["padded"], r["step_s"] * 1e3, base / r["step_s"], r["first_step_s"],
             r["peak_mib"] if r["peak_mib"] is not None else "-"] for n, r in joint.items()]
    print(markdown_table(["option", "width", "batch", "padded", "ms/step", "speed-up", "first step s", "peak MiB"],
                         rows, {"ms/step": ".0f", "speed-up": ".2f", "first step s": ".1f", "peak MiB": ".0f"}))
    fbase = infer["float32"]["fps"]
    rows = [[k, r["size"], r["fps"], r["fps"] / fbase, r["first_call_s"], r["peak_mib"] if r["peak_mib"] is not None
             else "-"] for k, r in infer.items()]
    print(markdown_table(["SGAN-F inference", "width", "FPS", "speed-up", "first call s", "peak MiB"], rows,
                         {"FPS": ".2f", "speed-up": ".2f", "first call s": ".1f", "peak MiB": ".0f"}))
    out = {"machine": machine(), "device": str(dev), "joint_step": joint, "sgan_f_inference_256": infer}
    path = write_json(RESULTS / f"train_options_{dev.type}.json", out)
    print(f"wrote {path}")
    return out


if __name__ == "__main__":
    main()
