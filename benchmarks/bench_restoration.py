"""Restoration: each SGAN variant and width, the Wiener-UNet plug-in, and Wiener: ms/image against PSNR on held-out
scenes.

A randomly initialised network's PSNR means nothing, so every network (SGAN-B/E/F and `model=wiener_unet`) is first
trained briefly by the project's own Trainer on the +experiment=baseline config (composed with Hydra),
each from the same seed, the same training batches and the same steps per width. Then every method restores the
*same* simulated sensor images of the test split (built-in scenes cell and chelsea, never trained on) at alpha_l =
0 and 1e6, scored by the project's Evaluator (codesign/train/evaluation.py: PSNR / SSIM of
codesign/models/quality.py on the field of view).

Inference time only (untrained networks, no PSNR), full scale: every network at the paper's geometry (input
padded to 384, as 256 px images), cpu and paper widths on a CPU, the paper width on a GPU, and classical Wiener
at the same size (docs/models.md Sec. 7).

    python -m benchmarks --only restoration [--scale full]
"""
from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path

import torch
import torch.nn.functional as F

from benchmarks.common import (Report, compose, cuda_sync, device, fresh_model, machine, markdown_table, peak_cuda_mib,
                               restorer, time_error_plot, timeit, write_json)

METHODS = ("sgan_b", "sgan_e", "sgan_f", "wiener_unet")  # model=<name>; each trained with the same budget
ALPHAS = (0.0, 1e6)


def plan(scale: str, dev: torch.device) -> dict:
    """Geometry, batch, training steps per width; ``timed``: [width, input size (None: the trained one)] timed only
    (untrained)."""
    if scale == "quick":  # ~2 min on 2 CPU cores; a dozen steps of the cpu width only learn the image's mean
        return dict(image=64, padded=96, batch=4, train={"tiny": 40}, timed=[["cpu", None]], repeats=10)
    if dev.type == "cuda":  # the paper's depth needs a 256-px input (coarse scale >= 2^7): all three widths train
        return dict(image=128, padded=256, batch=8, train={"tiny": 1000, "cpu": 1000, "paper": 300},
                    timed=[["paper", 384]], repeats=20)
    return dict(image=64, padded=96, batch=4, train={"tiny": 200, "cpu": 150}, timed=[["cpu", 384], ["paper", 384]],
                repeats=5)


def _config(method: str, size: str, p: dict, steps: int):
    return compose(["+experiment=baseline", f"model={method}", f"model.size={size}",
                 f"data.image_size={p['image']}", f"data.padded_size={p['padded']}", f"data.batch_size={p['batch']}",
                 f"trainer.steps={steps}", "trainer.val_every=0", "trainer.checkpoint_every=0",
                 "trainer.image_every=0",
                 # constant learning rate: the Sec. 6.2 decay squeezed into a few dozen steps would stop training
                    # after its first quarter (docs/results_log.md, restorers after 15 minutes of CPU)
                    "trainer.first_fraction=1.0"])


def _train(cfg, data, start: dict, dev: torch.device):
    """(model, generators, steps, seconds): the baseline experiment's model + trainer, no TensorBoard."""
    from codesign.train.model_setup import build_trainer

    model = fresh_model(cfg)
    data.load_state_dict(start)  # every method sees the same training batches
    with tempfile.TemporaryDirectory() as tmp:  # the trainer's final checkpoint is not kept
        trainer = build_trainer(cfg, model, data, Path(tmp), dev, 0)
        t0 = time.perf_counter()
        trainer.fit(progress_every=10**9)
        seconds = time.perf_counter() - t0
    return model, trainer.restoring_modules(), trainer.step, seconds


def _timed(fn, repeats: int, dev: torch.device) -> tuple[float, float | None]:
    """(ms per call, peak CUDA MiB or None), no gradient."""
    peak_cuda_mib(dev, reset=True)
    with torch.no_grad():
        sec = timeit(fn, repeats, warmup=2 if dev.type == "cuda" else 1, sync=cuda_sync(dev))
    return 1e3 * sec, peak_cuda_mib(dev)


def _baseline_timers(data, batch: dict, calib: dict, n: int) -> dict:
    """Batch-1 closures doing exactly what the Evaluator does for the sensor and Wiener methods."""
    from codesign.train.evaluation import remove_black_level, replicate_pad
    from codesign.camera import field_of_view as centre
    from codesign.models.wiener import classical_wiener

    one = {"sensor": batch["sensor"][:1], "read_noise_mean_e": batch["read_noise_mean_e"][:1]}
    fw, otf = data.camera.sensor.full_well_e, data.otf

    def affine(name, x):
        a, c = calib[name]
        return (a * x + c).clamp(0, 1)

    return {"sensor": lambda: affine("sensor", centre(remove_black_level(one, fw), n)),
            "wiener": lambda: affine("wiener", centre(classical_wiener(
                replicate_pad(remove_black_level(one, fw), n), otf, calib["nsr"]["wiener"]), n))}


def measure(scale: str) -> dict:
    from codesign.data.params import laser_preset_name
    from codesign.train.evaluation import Evaluator
    from codesign.camera import field_of_view as centre
    from codesign.train.data import build_simulated_data
    from codesign.models import classical_wiener, otf_from_kernel, parameter_count

    dev = device()
    p = plan(scale, dev)
    data = build_simulated_data(_config("sgan_b", "tiny", p, 1), dev, 0)  # physics + scenes: the same for all
    start = data.state_dict()
    names = data.source.split_names("test")
    scenes = data.source.fixed_batch(names, data.camera.scene_size)
    batches = {a: data.preset_batch(scenes, laser_preset_name(a), seed=1000 + j) for j, a in enumerate(ALPHAS)}
    tuning = data.validation_batch(8)  # train split: the baselines' nsr and gain/offset are tuned here
    rows, calib, n = [], None, data.image_size
    for size, steps in p["train"].items():
        for method in METHODS:
            model, gens, done, seconds = _train(_config(method, size, p, steps), data, start, dev)
            ev = Evaluator(model, gens, data, perceptual={}, batch_size=8)
            calib = ev.tune(tuning)
            scores = {a: ev.score(ev.restore_all(b), centre(b["scene"], n).clamp(0, 1)) for a, b in batches.items()}
            x1 = batches[ALPHAS[-1]]["sensor"][:1]
            ms, mem = _timed(lambda: model.restore(x1, data.otf, gens), p["repeats"], dev)
            column = model.method  # the restorer's column of the evaluation table
            rows.append({"method": method, "size": size, "params": sum(parameter_count(g) for g in gens),
                         "ms_per_image": ms, "peak_cuda_mib": mem, "steps": done, "train_seconds": seconds,
                         "scores": {str(a): scores[a][column] for a in ALPHAS}})
            print(f"  {method} {size:5s} {done:5d} steps {seconds:7.1f} s  {ms:8.2f} ms/image  PSNR "
                  + "  ".join(f"{_name(a)}: {scores[a][column]['psnr']:.2f}" for a in ALPHAS), flush=True)
            model = gens = None  # free before the next width (GPU memory)
    # sensor (identity + gain/offset: the floor) and Wiener: independent of the network (tuned on the same set)
    for name, fn in _baseline_timers(data, batches[ALPHAS[-1]], calib, n).items():
        ms, mem = _timed(fn, max(p["repeats"], 20), dev)
        rows.append({"method": name, "size": "-", "params": 0, "ms_per_image": ms, "peak_cuda_mib": mem,
                     "steps": 0, "train_seconds": 0.0, "scores": {str(a): scores[a][name] for a in ALPHAS}})
    wiener_timed = set()
    for size, padded in p["timed"]:  # inference time only: untrained, no PSNR
        padded = padded or p["padded"]
        tag = f" (input {padded})" if padded != p["padded"] else ""
        x1 = F.pad(batches[ALPHAS[-1]]["sensor"][:1], [(padded - p["padded"]) // 2] * 4)
        otf = otf_from_kernel(data.camera.frozen_optics().kernel, padded).to(dev)
        for method in METHODS:
            model = restorer(method, size).to(dev)
            model.check_input_size(padded)
            ms, mem = _timed(lambda: model.restore(x1, otf),
                             1 if size == "paper" and dev.type != "cuda" else p["repeats"], dev)
            rows.append({"method": method, "size": size + tag,
                         "params": sum(parameter_count(g) for g in model.generators()), "ms_per_image": ms,
                         "peak_cuda_mib": mem, "steps": 0, "train_seconds": 0.0, "scores": None})
            print(f"  {method} {size}{tag} (timed only) {ms:8.1f} ms/image", flush=True)
            model = None
        if tag and padded not in wiener_timed:  # classical Wiener at the same input size (no tuning: timing only)
            wiener_timed.add(padded)
            ms, mem = _timed(lambda: classical_wiener(x1, otf, calib["nsr"]["wiener"]), max(p["repeats"], 20), dev)
            rows.append({"method": "wiener", "size": "-" + tag, "params": 0, "ms_per_image": ms,
                         "peak_cuda_mib": mem, "steps": 0, "train_seconds": 0.0, "scores": None})
    return {"machine": machine(), "device": str(dev), "scale": scale, "plan": p, "test_scenes": names,
            "alphas": list(ALPHAS), "calibration": calib, "rows": rows}


LABEL = {"sgan_b": "SGAN-B", "sgan_e": "SGAN-E", "sgan_f": "SGAN-F", "wiener_unet": "Wiener-UNet",
         "wiener": "Wiener (tuned nsr)", "sensor": "sensor (identity + gain/offset)"}


def _name(a: float) -> str:
    return "0" if a == 0 else f"1e{round(math.log10(a))}"


def report(res: dict, out: Path) -> Report:
    from codesign.train.evaluation import NSR_GRID

    p, alphas = res["plan"], res["alphas"]
    header = ["method", "size", "params", "ms/image"] + \
        [f"alpha_l={_name(a)}: PSNR / SSIM / PSNR matched" for a in alphas] + ["train steps", "train s"]
    table = []
    for r in res["rows"]:
        cells = [f"{r['scores'][str(a)]['psnr']:.2f} / {r['scores'][str(a)]['ssim']:.3f} / "
                 f"{r['scores'][str(a)]['psnr_matched']:.2f}" if r["scores"] else "-" for a in alphas]
        trained = [r["steps"], r["train_seconds"]] if r["steps"] else ["-", "-"]
        table.append([LABEL[r["method"]], r["size"], r["params"], r["ms_per_image"], *cells, *trained])
    md = markdown_table(header, table, {"ms/image": ".3g", "train s": ".1f"})
    print(md)
    figures = []
    for a in alphas:
        series = {}
        for r in res["rows"]:
            if r["scores"]:
                series.setdefault(LABEL[r["method"]], []).append(
                    (r["ms_per_image"], r["scores"][str(a)]["psnr"], r["size"] if r["size"] != "-" else ""))
        figures.append(time_error_plot(
            out / f"restoration_alpha_{_name(a)}.png", series, f"ms / image (batch 1, {res['device']})",
            "PSNR on held-out scenes [dB] (higher is better)",
            f"restoration at alpha_l = {_name(a)}: {p['image']} px, short trainings", logy=False))
    steps = ", ".join(f"{k} {v}" for k, v in p["train"].items())
    notes = [
        f"Each SGAN variant and the Wiener-UNet plug-in (`model=wiener_unet`: learnable Wiener deconvolution of "
        "features + residual UNet, Charbonnier L1 only, no critics) is trained in process by the project's "
        f"Trainer on the +experiment=baseline config: {p['image']} px images padded to {p['padded']}, "
        f"batch {p['batch']}, steps per width: {steps} (the same budget for every network), constant learning "
        "rate (trainer.first_fraction=1), same seed and same training batches for every network, SGAN-E/F without "
        "their VGG term (no weights here). **These are short CPU-budget trainings, not the paper's results** (the "
        "paper trains 400 epochs of 10,000 images).",
        f"All methods restore the same simulated sensor images of the built-in test split "
        f"({', '.join(res['test_scenes'])}, never trained on) at the figure settings with alpha_l = "
        f"{', '.join(_name(a) for a in alphas)} (laser on axis), scored by codesign.train.evaluation.Evaluator: "
        "PSNR / SSIM against the scene on the field of view, and PSNR after a per-image gain/offset match (PSNR "
        "aff.). Wiener: classical Wiener with the true PSF, its nsr picked on 8 training-split images (best "
        f"PSNR matched on a log grid; chosen: {res['calibration']['nsr']['wiener']:.3g}), then a global gain/offset; "
        "sensor: the raw image with its black level removed and a global gain/offset, the floor."
        + (" The tuned nsr is the top of the grid: at this noise and MTF the Wiener filter degenerates to a matched "
           "filter (docs/results_log.md, restorers after 15 minutes of CPU, item 3)."
           if res["calibration"]["nsr"]["wiener"] >= max(NSR_GRID) else ""),
        f"ms/image: median of repeats at batch 1 on {res['device']}, eval mode, no gradient, the whole network "
        f"(SGAN: the sandwich G2(G_v(G1(s)))) on the {p['padded']}-px input; threads {res['machine']['threads']}. "
        "Framework default: "
        "`python -m codesign +experiment=baseline` trains SGAN-B at the cpu width, 128 px padded to 192, batch 4, "
        "300 steps with the Sec. 6.2 schedule; `model.size=paper` is the supplement's width."
        + (" Timed only (untrained, no PSNR): " + ", ".join(
            f"{w} width" + (f" on a {px}-px input" if px else "") for w, px in p["timed"]) + "."
           + (" The paper width's depth needs an input of at least 256 px." if any(w == "paper" for w, _ in p["timed"])
              else "") if p["timed"] else ""),
    ]
    return Report("restoration", "Restoration: SGAN variants and widths against Wiener, ms/image vs PSNR",
                  [md], figures, notes)


def run(scale: str, out: Path) -> Report:
    out.mkdir(parents=True, exist_ok=True)
    res = measure(scale)
    write_json(out / "restoration.json", res)
    return report(res, out)


if __name__ == "__main__":
    from benchmarks.__main__ import standalone

    standalone(run)
