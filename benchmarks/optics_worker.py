"""One isolated optics timing: prints a JSON line with forward/backward seconds, LSR and peak memory.

python -m benchmarks.optics_worker --samples 384 [--propagator mft|fft] [--fft-n 4096] [--dtype float32]
"""
from __future__ import annotations

import argparse
import json

import torch

from benchmarks.common import peak_rss_mb


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=float, required=True, help="pupil samples across the aperture")
    ap.add_argument("--propagator", default="mft", choices=["mft", "fft"])
    ap.add_argument("--fft-n", type=int, default=None)
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--focal-n", type=int, default=640)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    from codesign.engine.psf_task import time_forward_backward
    from codesign.optics import OpticalSystem, OpticsSpec, metrics
    from codesign.optics.masks import HalfRingMask

    rss0 = peak_rss_mb()
    spec = OpticsSpec.with_samples_across(a.samples, propagator=a.propagator, fft_n=a.fft_n, focal_n=a.focal_n)
    dtype = torch.float32 if a.dtype == "float32" else torch.float64
    system = OpticalSystem(spec, dtype=dtype)
    mask = HalfRingMask(system.grid, spec.aperture_diameter_m)
    fwd, bwd = time_forward_backward(system, mask, 16.0, a.repeats)
    with torch.no_grad():
        phase = mask.phase()
        psf = system.psf(phase)
        lsr = system.refined_peak(phase, psf) / system.uncoded_peak
        smooth = float(metrics.lsr_smooth(psf, system.uncoded_peak))
    print(json.dumps({
        "samples": a.samples, "grid_n": spec.grid_n, "propagator": system.method,
        "fft_n": getattr(system.propagator, "fft_n", None), "dtype": a.dtype, "threads": a.threads,
        "seconds_forward": fwd, "seconds_backward": bwd, "seconds_total": fwd + bwd, "lsr": lsr,
        "lsr_smooth": smooth, "peak_rss_mb": peak_rss_mb(), "baseline_rss_mb": rss0,
    }))


if __name__ == "__main__":
    main()
