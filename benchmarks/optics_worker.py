"""One isolated optics timing: prints a JSON line with forward/backward seconds, LSR, MTF, PSF error, peak memory.

python -m benchmarks.optics_worker --samples 384 [--propagator mft|fft] [--fft-n 4096] [--dtype float32]
    [--save PSF.pt] [--reference PSF.pt]

A fresh process per configuration, so that the peak resident memory (CPU) or peak allocated memory (CUDA) is this
configuration's own. ``--reference`` gives the relative L1 error of the PSF against a saved (float64) PSF on the
same focal window; ``--save`` writes this PSF (float64) for later runs to compare with.
"""
from __future__ import annotations

import argparse
import json

import torch

from benchmarks.common import peak_cuda_mib, peak_rss_mb


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=float, required=True, help="pupil samples across the aperture")
    ap.add_argument("--propagator", default="mft", choices=["mft", "fft"])
    ap.add_argument("--fft-n", type=int, default=None)
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--focal-n", type=int, default=640)
    ap.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    ap.add_argument("--save", default=None)
    ap.add_argument("--reference", default=None)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    from codesign.design.merit import evaluate_mask, time_forward_backward
    from codesign.optics import OpticalSystem, OpticsSpec
    from codesign.optics.masks import HalfRingMask

    dev = torch.device("cuda" if a.device == "auto" and torch.cuda.is_available() else
                       ("cpu" if a.device == "auto" else a.device))
    rss0 = peak_rss_mb()
    spec = OpticsSpec.with_samples_across(a.samples, propagator=a.propagator, fft_n=a.fft_n, focal_n=a.focal_n)
    dtype = torch.float32 if a.dtype == "float32" else torch.float64
    system = OpticalSystem(spec, dtype=dtype, device=dev)
    mask = HalfRingMask(system.grid, spec.aperture_diameter_m)
    peak_cuda_mib(dev, reset=True)
    fwd, bwd = time_forward_backward(system, mask, 16.0, a.repeats)
    peak_gpu = peak_cuda_mib(dev)
    values, arrays = evaluate_mask(system, mask, (0.0, 0.5), 16.0)
    psf = arrays["psf"].detach().to("cpu", torch.float64)
    err = None
    if a.reference:
        ref = torch.load(a.reference)
        err = float((psf - ref).abs().sum() / ref.abs().sum())
    if a.save:
        torch.save(psf, a.save)
    print(json.dumps({
        "samples": a.samples, "grid_n": spec.grid_n, "propagator": system.method,
        "fft_n": getattr(system.propagator, "fft_n", None), "dtype": a.dtype, "threads": a.threads,
        "device": str(dev), "seconds_forward": fwd, "seconds_backward": bwd, "seconds_total": fwd + bwd,
        "lsr": values["lsr"], "lsr_smooth": values["lsr_smooth"], "mtf_mean": values["mtf_mean"],
        "psf_rel_l1": err, "peak_rss_mb": peak_rss_mb(), "baseline_rss_mb": rss0, "peak_gpu_mb": peak_gpu,
    }))


if __name__ == "__main__":
    main()
