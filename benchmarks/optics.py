"""Optics benchmarks: LSR convergence against pupil sampling (float64), and the speed target of issue 2.

    python -m benchmarks.optics convergence   # table of LSR/BSR/MTF per variant and sampling, JSON + PNG
    python -m benchmarks.optics speed         # fwd+bwd time at the coarsest converged sampling vs the paper's path
"""
from __future__ import annotations

import argparse
import time

import torch

from benchmarks.common import RESULTS, machine, run_isolated, write_result

VARIANTS = [  # (convention, m_range, harmonic_sign)
    ("atan2", (1, 17), "printed"), ("atan2", (0, 17), "printed"),
    ("atan", (1, 17), "printed"), ("atan", (0, 17), "printed"),
    ("atan2", (1, 17), "fourier"), ("atan2", (0, 17), "fourier"),
]
SAMPLINGS = [192, 256, 320, 384, 512, 768, 1024, 1536, 2048]


def convergence(samplings: list[int]) -> dict:
    from codesign.design.merit import evaluate_mask
    from codesign.optics import OpticalSystem, OpticsSpec
    from codesign.optics.masks import HalfRingMask

    rows = []
    for s in samplings:
        t0 = time.perf_counter()
        spec = OpticsSpec.with_samples_across(s)
        system = OpticalSystem(spec, dtype=torch.float64)
        for conv, mr, sign in VARIANTS:
            mask = HalfRingMask(system.grid, spec.aperture_diameter_m, convention=conv, m_range=mr,
                                harmonic_sign=sign)
            vals, _ = evaluate_mask(system, mask, (0.0, 0.5), 16.0)
            rows.append({"samples": s, "grid_n": spec.grid_n, "convention": conv, "m_range": list(mr),
                         "harmonic_sign": sign, **{k: vals[k] for k in (
                             "lsr", "lsr_sampled", "lsr_smooth", "bsr", "mtf_mean", "mtf_min",
                             "psf_energy_in_window")}})
        print(f"samples {s:5d} (grid {spec.grid_n}): {time.perf_counter() - t0:6.1f} s", flush=True)
    return {"machine": machine(), "rows": rows}


def _key(r: dict) -> tuple:
    return r["convention"], tuple(r["m_range"]), r["harmonic_sign"]


def print_convergence(data: dict) -> None:
    rows = data["rows"]
    finest = max(r["samples"] for r in rows)
    ref = {_key(r): r for r in rows if r["samples"] == finest}
    print(f"\nLSR relative to the {finest}-sample float64 value (published r_n, theta_n):")
    print(f"{'samples':>8} " + " ".join(f"{c + str(m) + s[0]:>18}" for c, m, s in ref))
    for s in sorted({r["samples"] for r in rows}):
        line = [r for r in rows if r["samples"] == s]
        print(f"{s:>8} " + " ".join(f"{r['lsr']:10.5g} {100 * (r['lsr'] / ref[_key(r)]['lsr'] - 1):+6.2f}%"
                                     for r in line))


def plot_convergence(data: dict) -> None:
    from codesign.io.files import save_figure
    from codesign.io.plots import plt

    rows = data["rows"]
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for key in dict.fromkeys(_key(r) for r in rows):
        pts = sorted((r["samples"], r["lsr"]) for r in rows if _key(r) == key)
        ax.plot(*zip(*pts), "o-", label=f"{key[0]}, m={key[1][0]}..{key[1][1]}, {key[2]}")
    ax.axvline(384, color="0.5", ls=":", label="default (384)")
    ax.set(xscale="log", yscale="log", xlabel="pupil samples across the aperture", ylabel="LSR (float64)",
           title="LSR convergence, published half-ring values")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    save_figure(RESULTS / "optics_convergence.png", fig)


def speed(samples: int, repeats: int) -> dict:
    fast = run_isolated("benchmarks.optics_worker", ["--samples", str(samples), "--repeats", str(repeats)])
    paper = run_isolated("benchmarks.optics_worker", ["--samples", "1024.0", "--propagator", "fft",
                                                      "--fft-n", "4096", "--repeats", str(max(1, repeats // 2))])
    sweep = [run_isolated("benchmarks.optics_worker", ["--samples", str(s), "--repeats", str(repeats)])
             for s in (192, 256, 320, 384, 512, 768, 1024)]
    return {"machine": machine(), "default": fast, "paper_fft4096": paper, "mft_sweep": sweep,
            "speedup": paper["seconds_total"] / fast["seconds_total"]}


def plot_speed(data: dict, ref_lsr: float) -> None:
    from codesign.io.files import save_figure
    from codesign.io.plots import plt

    fig, ax = plt.subplots(figsize=(6, 4))
    sw = data["mft_sweep"]
    ax.plot([r["seconds_total"] for r in sw], [abs(r["lsr"] / ref_lsr - 1) for r in sw], "o-",
            label="MFT onto the 640 window, float32")
    for r in sw:
        ax.annotate(f"{int(r['samples'])}", (r["seconds_total"], abs(r["lsr"] / ref_lsr - 1)), fontsize=7)
    p = data["paper_fft4096"]
    ax.plot([p["seconds_total"]], [abs(p["lsr"] / ref_lsr - 1)], "s", label="paper: 4096 FFT + resampling")
    ax.axhline(0.01, color="0.5", ls=":", label="1% of converged")
    ax.set(xscale="log", yscale="log", xlabel="forward + backward [s] (2 threads)",
           ylabel="|LSR / LSR_converged - 1|", title="PSF -> smooth LSR: run time against error")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    save_figure(RESULTS / "optics_speed.png", fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["convergence", "speed", "all"])
    ap.add_argument("--samplings", default=",".join(map(str, SAMPLINGS)))
    ap.add_argument("--samples", type=int, default=384, help="sampling timed against the paper path")
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args()
    torch.set_num_threads(2)
    if a.what in ("convergence", "all"):
        data = convergence([int(s) for s in a.samplings.split(",")])
        write_result("optics_convergence", data)
        print_convergence(data)
        plot_convergence(data)
    if a.what in ("speed", "all"):
        import json

        conv = json.loads((RESULTS / "optics_convergence.json").read_text())["rows"]
        finest = max(r["samples"] for r in conv)
        ref = next(r["lsr"] for r in conv if r["samples"] == finest and r["convention"] == "atan2"
                   and r["m_range"] == [1, 17] and r["harmonic_sign"] == "printed")
        data = speed(a.samples, a.repeats)
        data["converged_float64_lsr"] = ref
        write_result("optics_speed", data)
        plot_speed(data, ref)
        for name in ("default", "paper_fft4096"):
            r = data[name]
            print(f"{name:>14}: grid {r['grid_n']} {r['propagator']} fwd {r['seconds_forward']:.4f} s "
                  f"bwd {r['seconds_backward']:.4f} s total {r['seconds_total']:.4f} s lsr {r['lsr']:.5g} "
                  f"(float64 converged {ref:.5g}, {100 * (r['lsr'] / ref - 1):+.2f}%) peak RSS "
                  f"{r['peak_rss_mb']:.0f} MiB (baseline {r['baseline_rss_mb']:.0f})")
        print(f"speed-up {data['speedup']:.1f}x")


if __name__ == "__main__":
    main()
