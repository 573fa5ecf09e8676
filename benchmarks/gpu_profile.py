"""Where a restoration's inference time goes on the GPU: wall time against the GPU's busy time and the number of
kernel launches (torch.profiler), SGAN-F at the cpu and paper widths, float32 and bf16, batch 1, 256 px padded to
384. The first GPU campaign (docs/gpu.md) found the forward launch-bound: 4.7k-11k kernels per image, the GPU busy
a third to three quarters of the wall time.

    python -m benchmarks.gpu_profile --out benchmarks/results/gpu      # on a CUDA machine: profile_sgan_f.txt
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile

from benchmarks.common import compose, write_text


def profile_cell(model, x, otf, mode: str, repeats: int = 5) -> tuple[str, str]:
    """(one summary line, the profiler's table) of ``model.restore`` on ``x`` in ``mode`` (float32 or bf16)."""
    gens = model.generators()

    def call():
        with torch.no_grad(), torch.autocast("cuda", dtype=torch.bfloat16, enabled=mode == "bf16"):
            model.restore(x, otf, gens)

    for _ in range(3):
        call()
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(repeats):
        call()
    torch.cuda.synchronize()
    wall = (time.perf_counter() - t0) / repeats
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        call()
        torch.cuda.synchronize()
    ka = prof.key_averages()
    # the device's own events (kernels, copies): an operator's row repeats its kernels' time, so summing every row
    # counts it twice (as the first campaign's prototype of this script did; docs/gpu.md uses the table's footer)
    dev_rows = [e for e in ka if e.device_type == DeviceType.CUDA and not e.is_user_annotation]
    busy_ms = sum(e.self_device_time_total for e in dev_rows) / 1e3
    launches = sum(e.count for e in dev_rows)
    line = f"wall {1e3 * wall:.1f} ms, GPU busy {busy_ms:.1f} ms, {launches} kernel calls"
    return line, ka.table(sort_by="self_device_time_total", row_limit=18, max_name_column_width=60)


def main(argv=None) -> int:
    from benchmarks.gpu import _otf
    from codesign.config.runtime import to_container
    from codesign.models import build_restorer

    ap = argparse.ArgumentParser(prog="python -m benchmarks.gpu_profile", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="folder for profile_sgan_f.txt")
    a = ap.parse_args(argv)
    if not torch.cuda.is_available():
        ap.error(f"no CUDA device visible (torch {torch.__version__}): this profiles the GPU")
    dev, parts = torch.device("cuda"), []
    for width in ("cpu", "paper"):
        model = build_restorer(to_container(compose(["model=sgan_f", f"model.size={width}"]).model)).to(dev)
        x, otf = torch.rand(1, 1, 384, 384, device=dev), _otf(384, dev)
        for mode in ("float32", "bf16"):
            line, table = profile_cell(model, x, otf, mode)
            head = f"== sgan_f {width} {mode} batch 1: {line}"
            print(head, flush=True)
            parts += [head, table]
    a.out.mkdir(parents=True, exist_ok=True)
    write_text(a.out / "profile_sgan_f.txt", "\n".join(parts) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
