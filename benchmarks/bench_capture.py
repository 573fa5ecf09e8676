"""Restoring a real capture: seconds per frame of the shipped restorer (``checkpoint=pretrained``, a network that
takes any size) on sensor-resolution captures, binned to its working scale or at full resolution.

Cases: the paper's 2532 x 2532 frame at the 256 px scale (bin 2532 / 256, as the paper downsampled) and at full
resolution (bin 1, the decoder in 512 px tiles after one global deconvolution), and a 1920 x 1080 frame of the same
5.4 um sensor at both. Each time is the whole of codesign/models/capture.py's restore_capture: binning, the OTF on
the capture's canvas, the network (the PSF of the published mask computed once before, as a run does). The capture's
content does not change the work (a smooth field with a saturated laser spot). Median of ``repeats`` after one
warm-up call.

    python -m benchmarks --only capture [--scale full]
"""
from __future__ import annotations

import time
from pathlib import Path

import torch

from benchmarks.common import Report, machine, markdown_table, timeit, write_json
from codesign.camera import build_camera
from codesign.models.capture import capture_geometry, restore_capture
from codesign.models.restorer import parameter_count
from codesign.train.resume import load_trained

CASES = (("2532 x 2532", (2532, 2532), 2532 / 256), ("2532 x 2532", (2532, 2532), 1.0),
         ("1920 x 1080", (1080, 1920), 2532 / 256), ("1920 x 1080", (1080, 1920), 1.0))


def capture(shape: tuple[int, int], full_well_dn: float) -> torch.Tensor:
    """Counts [DN]: a smooth field at a third of the full well, a saturated disc of 40 px radius off centre."""
    h, w = shape
    y, x = torch.meshgrid(torch.linspace(-1, 1, h, dtype=torch.float64), torch.linspace(-1, 1, w, dtype=torch.float64),
                          indexing="ij")
    counts = full_well_dn * (0.33 + 0.1 * torch.sin(7 * x) * torch.cos(5 * y))
    spot = (y * h / 2 - h / 5) ** 2 + (x * w / 2 + w / 6) ** 2 < 40**2
    return torch.where(spot, torch.full_like(counts, full_well_dn), counts)


def measure(scale: str) -> dict:
    model, generators, cfg, _ = load_trained("pretrained", torch.device("cpu"))
    if not model.any_size:
        raise SystemExit(f"bench_capture: the shipped restorer ({model.kind}) takes only its training size")
    cam = build_camera(cfg, torch.device("cpu"))
    psf, sensor = cam.frozen_optics().state.psf, cam.sensor
    full_well_dn = sensor.gain_dn_per_e * sensor.full_well_e
    rows = []
    for name, shape, factor in CASES:
        counts = capture(shape, full_well_dn)
        geometry = capture_geometry(shape, factor, sensor.pixel_pitch_m, cam.optics.focal_extent_m)
        tile = 512 if geometry.canvas[0] * geometry.canvas[1] > 1536**2 else None
        repeats = 10 if factor > 1 else (1 if scale == "quick" else 3)
        run = lambda: restore_capture(model, counts, psf, sensor, geometry, generators, tile)  # noqa: E731
        seconds = timeit(run, repeats)
        rows.append({"capture": name, "bin": round(factor, 4), "network_px": list(geometry.size),
                     "canvas": list(geometry.canvas), "kernel_px": geometry.kernel, "tile": tile,
                     "repeats": repeats, "seconds": seconds, "frames_per_s": 1 / seconds})
    return {"machine": machine(), "network": model.summary(), "parameters": sum(
        parameter_count(g) for g in model.generators()), "rows": rows, "date": time.strftime("%Y-%m-%d")}


def report(res: dict, out: Path) -> Report:
    table = markdown_table(["capture", "bin", "network px", "tile", "s / frame", "frames / s"],
                           [[r["capture"], r["bin"], "x".join(map(str, r["network_px"])), r["tile"] or "whole",
                             r["seconds"], r["frames_per_s"]] for r in res["rows"]], {"s / frame": ".3f",
                                                                                      "frames / s": ".2f"})
    return Report("capture", "Restoring a real capture (the shipped restorer, any size)", [table],
                  notes=[f"{res['network']['network']} ({res['parameters'] / 1e6:.2f} M parameters) on "
                         f"{res['machine']['cores']} cores, torch {res['machine']['torch']}; binning, OTF and "
                         "network included, the PSF computed once before"])


def run(scale: str, out: Path) -> Report:
    res = measure(scale)
    write_json(out / "capture.json", res)
    rep = report(res, out)
    for t in rep.tables:
        print(t)
    return rep


if __name__ == "__main__":
    from benchmarks.__main__ import standalone

    standalone(run)
