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


def quality(run_dirs: list[str], speed_json: Path | None = None, tag: str = "") -> dict:
    """Rows (run, method, condition, metrics) from the runs' metrics.json; a markdown table on stdout; a plot of
    ms/image (from the speed results, CPU size) against PSNR at alpha_l = 1e6 when those results exist."""
    rows = []
    for d in run_dirs:
        m = json.loads((Path(d) / "metrics.json").read_text())
        for cond, table in m["evaluation"].items():
            for method, metrics in table.items():
                rows.append({"run": str(d), "variant": m.get("variant"), "method": method, "condition": cond,
                             "steps": m.get("steps"), "train_seconds": m.get("seconds"),
                             "scenes": ",".join(m.get("evaluation_scenes", [])), **metrics})
    _print_markdown(rows)
    speed = json.loads(speed_json.read_text()) if speed_json and speed_json.is_file() else None
    if speed:
        _plot(rows, speed, tag)
    return {"machine": machine(), "rows": rows}


def _label(row: dict) -> str:
    return {"sgan": row["variant"].replace("sgan_", "SGAN-").upper(),
            "g1_wiener": f"G1({row['variant'][-1].upper()}) + Wiener"}.get(row["method"], row["method"])


def _print_markdown(rows: list[dict]) -> None:
    conds = [c for c in ("laser_0", "laser_1e3", "laser_1e6") if any(r["condition"] == c for r in rows)]
    seen, methods = set(), []
    for r in rows:
        key = (r["method"], r["variant"]) if r["method"] in ("sgan", "g1_wiener") else (r["method"], None)
        if key not in seen:
            seen.add(key)
            methods.append(key)
    print("| method | " + " | ".join(f"{c}: PSNR / SSIM / PSNR aff." for c in conds) + " |")
    print("|---|" + "---|" * len(conds))
    for method, variant in methods:
        cells = []
        for c in conds:
            sel = [r for r in rows if r["condition"] == c and r["method"] == method
                   and (variant is None or r["variant"] == variant)]
            r = sel[0]
            cells.append(f"{r['psnr']:.2f} / {r['ssim']:.3f} / {r['psnr_affine']:.2f}")
        print(f"| {_label(sel[0])} | " + " | ".join(cells) + " |")


def _plot(rows: list[dict], speed: dict, tag: str = "") -> None:
    from codesign.io.plots import plt

    ms = {(r["variant"], r["size"]): r["ms_per_image"] for r in speed["rows"]}
    fig, ax = plt.subplots(figsize=(6, 4))
    for r in rows:
        if r["condition"] != "laser_1e6" or r["method"] not in ("sgan", "wiener"):
            continue
        x = ms.get((r["variant"], "cpu")) if r["method"] == "sgan" else ms.get(("wiener", "-"))
        if x is None:
            continue
        ax.scatter(x, r["psnr_affine"], label=_label(r))
        ax.annotate(_label(r), (x, r["psnr_affine"]), fontsize=7)
    ax.set(xscale="log", xlabel="ms / image (CPU, 2 threads)", ylabel="PSNR after gain/offset match [dB]",
           title="restoration at alpha_l = 1e6: time against quality")
    ax.grid(alpha=0.3)
    RESULTS.mkdir(parents=True, exist_ok=True)
    fig.savefig(RESULTS / f"restoration_quality{tag}.png", dpi=120, bbox_inches="tight")
    plt.close(fig)


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
    qp.add_argument("--speed", type=Path, default=RESULTS / "restoration_speed.json")
    args = ap.parse_args(argv)
    if args.cmd == "speed":
        res = speed(args.sizes, args.image, args.padded, args.repeats)
        print(write_result(f"restoration_speed{args.tag}", res))
    else:
        res = quality(args.runs, args.speed, args.tag)
        print(write_result(f"restoration_quality{args.tag}", res))


if __name__ == "__main__":
    main()
