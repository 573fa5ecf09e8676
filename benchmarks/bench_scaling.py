"""Scaling: how each cost grows with pupil size, image size and batch (fitted exponents).

(a) PSF forward + backward (mask parameters -> phase -> PSF -> smooth LSR and its gradient, timed by
    codesign.design.merit.time_forward_backward) against the pupil grid n, MFT onto the 640 x 640 window (the
    default propagator), compared with the flop model codesign.optics.propagation.mft_cost;
(b) sensor simulation (frozen published mask, kernels cached, alpha_l = 1e6 on axis, the figure's noise) against
    the network image size (padded 1.5x, as 256 -> 384) and against the batch;
(c) SGAN-B at the cpu width: forward (eval, no gradient) and forward + backward of the generators (train mode)
    against the padded input size and against the batch.
Each exponent k (cost ~ x^k) is a least-squares fit over the upper half of its sweep, where the fixed per-call
overhead is small against the cost; the table says which points.

    python -m benchmarks.bench_scaling --scale quick
"""
from __future__ import annotations

import math
from pathlib import Path

import torch

from benchmarks.common import (Report, cuda_sync, fit_exponent, machine, markdown_table, peak_cuda_mib,
                               published_sensor, timeit, write_json)

SWEEPS = {
    "quick": dict(samples=[192, 256, 384, 512, 768], images=[64, 96, 128, 192, 256, 384],
                  sim_batches=[1, 2, 4, 8, 16], sim_batch_image=128, nets=[64, 96, 128, 192, 256],
                  net_batches=[1, 2, 4, 8], net_batch_size=128, repeats=3),
    "full": dict(samples=[192, 256, 384, 512, 768, 1024, 1536], images=[64, 96, 128, 192, 256, 384, 512],
                 sim_batches=[1, 2, 4, 8, 16, 32], sim_batch_image=256, nets=[64, 96, 128, 192, 256, 384, 512],
                 net_batches=[1, 2, 4, 8, 16], net_batch_size=192, repeats=3),
}
# no 128 samples across: the 640-pixel window would alias at that pupil pitch (the spec refuses fewer than ~191)


def _fit(points: list[dict]) -> dict:
    """Exponent over the upper half of the sweep (at least 3 points)."""
    use = points[-max(3, (len(points) + 1) // 2):]
    xs, ys = [p["x"] for p in use], [p["seconds"] for p in use]
    k = fit_exponent(xs, ys)
    return {"exponent": k, "fit_x": xs, "fit_coefficient": math.exp(sum(math.log(y / x**k) for x, y in zip(xs, ys))
                                                                     / len(xs))}


def psf_sweep(s: dict, dev) -> list[dict]:
    """Whole chain (half-ring phase included) and propagation alone (phase fixed), forward + backward."""
    from codesign.design.merit import time_forward_backward
    from codesign.optics import OpticalSystem, OpticsSpec, metrics
    from codesign.optics.masks import HalfRingMask
    from codesign.optics.propagation import mft_cost

    chain, prop = [], []
    for samples in s["samples"]:
        spec = OpticsSpec.with_samples_across(samples, propagator="mft", focal_n=640)
        system = OpticalSystem(spec, device=dev)
        mask = HalfRingMask(system.grid, spec.aperture_diameter_m)  # the default mask (published, exact Bessel)
        peak_cuda_mib(dev, reset=True)
        fwd, bwd = time_forward_backward(system, mask, 16.0, s["repeats"])
        with torch.no_grad():
            phase = mask.phase()

        def propagate():  # the same loss from a fixed phase: what the mft_cost model counts
            ph = phase.clone().requires_grad_(True)
            metrics.lsr_smooth(system.psf(ph), system.uncoded_peak, 16.0).backward()

        sec = timeit(propagate, s["repeats"], sync=cuda_sync(dev))
        common = {"x": spec.grid_n, "samples_across": samples, "mft_flops": mft_cost(spec.grid_n, spec.focal_n)}
        chain.append({**common, "seconds": fwd + bwd, "seconds_forward": fwd, "seconds_backward": bwd,
                      "peak_cuda_mib": peak_cuda_mib(dev)})
        prop.append({**common, "seconds": sec})
        print(f"  PSF n={spec.grid_n:5d}: chain forward {1e3 * fwd:8.1f} ms + backward {1e3 * bwd:8.1f} ms; "
              f"propagation alone (forward + backward) {1e3 * sec:8.1f} ms", flush=True)
    fit = _fit(prop)
    fit["model_exponent"] = fit_exponent(fit["fit_x"], [p["mft_flops"] for p in prop if p["x"] in fit["fit_x"]])
    return [{"label": "PSF chain fwd+bwd vs pupil grid n (phase + MFT + LSR)", "points": chain, **_fit(chain)},
            {"label": "PSF propagation fwd+bwd vs pupil grid n (phase fixed)", "points": prop, **fit}]


def _simulator(image: int, dev):
    sim, state, key, _, _ = published_sensor(device=dev, image_size=image, padded_size=3 * image // 2)
    return sim, state, key


def sensor_sweeps(s: dict, dev) -> list[dict]:
    from codesign.data.params import preset_params

    def point(image: int, batch: int, x: int) -> dict:
        sim, state, key = _simulator(image, dev)
        scenes = torch.rand(batch, 1, sim.scene_size, sim.scene_size, generator=torch.Generator().manual_seed(0))
        scenes, params = scenes.to(dev), preset_params("laser_1e6", batch).to(dev, torch.float32)
        peak_cuda_mib(dev, reset=True)
        with torch.no_grad():
            sec = timeit(lambda: sim(scenes, params, state, seed=1, mask_key=key), s["repeats"], sync=cuda_sync(dev))
        print(f"  sensor image {image:4d} batch {batch:3d}: {1e3 * sec:8.1f} ms", flush=True)
        return {"x": x, "image": image, "batch": batch, "seconds": sec, "peak_cuda_mib": peak_cuda_mib(dev)}

    by_size = [point(n, 1, n) for n in s["images"]]
    by_batch = [point(s["sim_batch_image"], b, b) for b in s["sim_batches"]]
    return [{"label": "sensor simulation vs image size (batch 1)", "points": by_size, **_fit(by_size)},
            {"label": f"sensor simulation vs batch ({s['sim_batch_image']} px)", "points": by_batch,
             **_fit(by_batch)}]


def network_sweeps(s: dict, dev) -> list[dict]:
    from codesign.train.optim import init_weights
    from codesign.models import build_sgan, otf_from_kernel

    torch.manual_seed(0)
    model = build_sgan({"variant": "sgan_b", "size": "cpu"}).to(dev)
    init_weights(model)
    kernel = torch.rand(33, 33)

    def point(padded: int, batch: int, x: int, backward: bool) -> dict:
        x_in = torch.rand(batch, 1, padded, padded, device=dev)
        otf = otf_from_kernel(kernel / kernel.sum(), padded).to(dev)

        def fwd_bwd():
            out = model(x_in, otf)
            (out["i_b"].mean() + sum(b.mean() for b in out["b"])).backward()

        model.train(backward)
        model.zero_grad(set_to_none=True)
        peak_cuda_mib(dev, reset=True)
        with torch.set_grad_enabled(backward):
            sec = timeit(fwd_bwd if backward else (lambda: model(x_in, otf)), s["repeats"], sync=cuda_sync(dev))
        what = "forward+backward" if backward else "forward"
        print(f"  SGAN-B cpu {what:16s} input {padded:4d} batch {batch:3d}: {1e3 * sec:8.1f} ms", flush=True)
        return {"x": x, "padded": padded, "batch": batch, "seconds": sec, "peak_cuda_mib": peak_cuda_mib(dev)}

    curves = []
    for backward in (False, True):
        what = "forward+backward" if backward else "forward"
        size = [point(p, 1, p, backward) for p in s["nets"]]
        batch = [point(s["net_batch_size"], b, b, backward) for b in s["net_batches"]]
        curves += [{"label": f"SGAN-B cpu {what} vs input size (batch 1)", "points": size, **_fit(size)},
                   {"label": f"SGAN-B cpu {what} vs batch ({s['net_batch_size']} px)", "points": batch,
                    **_fit(batch)}]
    return curves


def _expected(c: dict) -> str:
    if "model_exponent" in c:
        return f"{c['model_exponent']:.2f} (mft_cost flops)"
    if c["label"].startswith("PSF"):
        return "2 (the phase: orders x rings per pupil sample)"
    return "1 (linear)" if "vs batch" in c["label"] else "2 (per pixel; the FFTs add a log)"


def plot(curves: list[dict], path: Path) -> Path:
    from codesign.io.files import save_figure
    from codesign.io.plots import plt

    panels = [("pupil grid n", [c for c in curves if c["label"].startswith("PSF")]),
              ("image / input size [px]", [c for c in curves if "vs image size" in c["label"]
                                           or "vs input size" in c["label"]]),
              ("batch", [c for c in curves if "vs batch" in c["label"]])]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.3))
    for ax, (xlabel, group) in zip(axes, panels):
        for i, c in enumerate(group):
            xs, ys = [p["x"] for p in c["points"]], [p["seconds"] for p in c["points"]]
            ax.plot(xs, ys, "o-", color=f"C{i}", ms=4, label=f"{c['label']}: k = {c['exponent']:.2f}")
            fx = c["fit_x"]
            ax.plot(fx, [c["fit_coefficient"] * x ** c["exponent"] for x in fx], ":", color=f"C{i}", lw=2)
            if "model_exponent" in c:  # flop model scaled to the largest measured point
                flops = [p["mft_flops"] for p in c["points"]]
                ax.plot(xs, [f * ys[-1] / flops[-1] for f in flops], "--", color="0.5",
                        label=f"mft_cost model (scaled): k = {c['model_exponent']:.2f}")
        ax.set(xscale="log", yscale="log", xlabel=xlabel, ylabel="seconds per call (median)")
        ticks = sorted({p["x"] for c in group for p in c["points"]})  # the measured sizes, in plain numbers
        ax.set_xticks(ticks, [str(t) for t in ticks], fontsize=7)
        ax.set_xticks([], minor=True)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=6)
    fig.suptitle("scaling: measured cost (solid), power-law fit over the upper half of each sweep (dotted)")
    return save_figure(path, fig)


def run(scale: str, out: Path) -> Report:
    dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    s = dict(SWEEPS[scale])
    if dev.type == "cuda" and scale == "full":  # the GPU only leaves its overhead regime at larger sizes
        s.update(nets=s["nets"] + [768, 1024], net_batches=s["net_batches"] + [32, 64])
    curves = psf_sweep(s, dev) + sensor_sweeps(s, dev) + network_sweeps(s, dev)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "scaling.json", {"machine": machine(), "device": str(dev), "scale": scale, "sweeps": s,
                                      "curves": curves})
    fig = plot(curves, out / "scaling.png")
    rows = [[c["label"], ", ".join(f"{p['x']}: {1e3 * p['seconds']:.3g}" for p in c["points"]),
             ", ".join(str(x) for x in c["fit_x"]), c["exponent"],
             _expected(c)] for c in curves]
    md = markdown_table(["cost", "x: ms (median)", "fitted over x =", "exponent k", "expected k"], rows,
                        {"exponent k": ".2f"})
    print(md)
    notes = [
        f"Median of {s['repeats']} calls after a warm-up on {dev} ({torch.get_num_threads()} threads). cost ~ x^k, "
        "k fitted (least squares in log-log) over the upper half of each sweep, where the fixed per-call overhead "
        "(Python, kernel launches, the laser's per-sample footprint) is small against the cost; the column "
        "'fitted over' lists those points. PSF: x is the pupil grid n (samples across the aperture plus the "
        "super-Gaussian edge), MFT onto the default 640 x 640 window (the default propagator at the default 384 "
        "samples across). 'chain': forward + backward of mask parameters -> half-ring phase (exact Bessel "
        "harmonics, the default mask) -> PSF -> smooth LSR (codesign.design.merit.time_forward_backward); "
        "'propagation': the same from a fixed phase, which is what the flop model mft_cost = 8 (m n^2 + m^2 n), "
        "m = 640, counts (its local exponent lies between 1 and 2 at these n; the 640 x 640 window terms are "
        "constant in n). The difference of the two is the phase, O(n^2) per harmonic and ring.",
        "Sensor: the direct path (the default) with the published mask frozen and its kernels cached (as in "
        "training), figure settings at alpha_l = 1e6 with the laser on axis, random scenes; padded size 1.5 x the "
        "image size. SGAN-B cpu width: the whole sandwich G2(G_v(G1(s))); forward in eval mode without gradient, "
        "forward + backward in train mode (backward of a mean of the outputs into the generators; no critics).",
    ]
    return Report("scaling", "Scaling: cost against pupil size, image size and batch (fitted exponents)", [md], [fig],
                  notes)


if __name__ == "__main__":
    from benchmarks.__main__ import standalone

    standalone(run)
