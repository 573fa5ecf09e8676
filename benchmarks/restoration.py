"""Restoration benchmarks: inference speed of each SGAN variant and size, and the quality table of trained runs.

    python -m benchmarks.restoration speed [--sizes cpu paper] [--image 256 --padded 384] [--repeats 3]
    python -m benchmarks.restoration quality RUN_DIR [RUN_DIR ...]

speed: ms per image (batch 1, eval mode, no grad) of the whole sandwich G2(G_v(G1(s))) at the network input size,
parameter counts, and classical Wiener for reference -> results/restoration_speed.json.
quality: collects metrics.json of baseline / evaluate runs into PSNR/SSIM per method at alpha_l = 0, 1e3, 1e6
(and the robustness stages) -> results/restoration_quality.json and .png (ms/image against PSNR).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from benchmarks.common import RESULTS, machine, write_result


def _time(fn, repeats: int) -> float:
    fn()  # warm-up (allocator, oneDNN primitives)
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - t0) / repeats


def speed(sizes, image: int, padded: int, repeats: int) -> dict:
    from codesign.models import VARIANTS, build_sgan, classical_wiener, otf_from_kernel, parameter_count

    dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    kernel = torch.rand(65, 65)
    otf = otf_from_kernel(kernel / kernel.sum(), padded).to(dev)
    x = torch.rand(1, 1, padded, padded, device=dev)
    rows = []
    for size in sizes:
        for variant in VARIANTS:
            model = build_sgan({"variant": variant, "size": size}).to(dev).eval()
            with torch.no_grad():
                def run():
                    model(x, otf)
                    if dev.type == "cuda":
                        torch.cuda.synchronize()
                sec = _time(run, repeats if size != "paper" or dev.type == "cuda" else 1)
            gens = sum(parameter_count(g) for g in model.generators())
            rows.append({"variant": variant, "size": size, "ms_per_image": 1e3 * sec, "fps": 1.0 / sec,
                         "parameters_generators": gens,
                         "parameters_critics": sum(parameter_count(d) for d in model.discriminators())})
            print(f"{variant} {size:6s} {1e3 * sec:10.1f} ms/image  {1 / sec:8.2f} FPS  generators "
                  f"{gens / 1e6:.2f} M", flush=True)
            del model
    sec = _time(lambda: classical_wiener(x, otf, 1e-2), max(repeats, 10))
    rows.append({"variant": "wiener", "size": "-", "ms_per_image": 1e3 * sec, "fps": 1.0 / sec,
                 "parameters_generators": 0, "parameters_critics": 0})
    print(f"classical wiener {1e3 * sec:.2f} ms/image")
    return {"machine": machine(), "device": str(dev), "image": image, "padded": padded, "rows": rows}


def quality(run_dirs: list[str]) -> dict:
    rows = []
    for d in run_dirs:
        m = json.loads((Path(d) / "metrics.json").read_text())
        ev = m["evaluation"]
        for cond, table in ev.items():
            for method, metrics in table.items():
                name = m.get("variant", "?") if method == "sgan" else method
                rows.append({"run": str(d), "variant": m.get("variant"), "method": name, "condition": cond,
                             "steps": m.get("steps"), "train_seconds": m.get("seconds"),
                             "scenes": ",".join(m.get("evaluation_scenes", [])), **metrics})
    return {"machine": machine(), "rows": rows}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    sp = sub.add_parser("speed")
    sp.add_argument("--sizes", nargs="+", default=["cpu", "paper"])
    sp.add_argument("--image", type=int, default=256)
    sp.add_argument("--padded", type=int, default=384)
    sp.add_argument("--repeats", type=int, default=3)
    sp.add_argument("--tag", default="")
    qp = sub.add_parser("quality")
    qp.add_argument("runs", nargs="+")
    qp.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    if args.cmd == "speed":
        res = speed(args.sizes, args.image, args.padded, args.repeats)
        print(write_result(f"restoration_speed{args.tag}", res))
    else:
        res = quality(args.runs)
        print(write_result(f"restoration_quality{args.tag}", res))


if __name__ == "__main__":
    main()
