"""How much memory a training run needs, estimated from its sizes before any work, against what the machine has.

A run that cannot fit dies mid-way with the operating system's out-of-memory kill (no swap) or CUDA's error, after
minutes of setup. The estimate:

  parameters   (generators + critics) x 4 copies (weights, gradients, Adam's two moments; +1 with EMA) x 4 bytes
  activations  batch x the bytes the restorer's forward pass saves for its backward, measured on one sample at the
               run's padded size (a real forward with gradients on the CPU: exact for this model and size), x
               ACTIVATION_FACTOR (the critics' passes and the backward's buffers, less the views the count
               double-counts and what the backward frees as it goes)
  simulation   batch x the scene crop's FFT plane x SIMULATION_BYTES (scene, irradiance, spectra, noise fields)
  laser halo   the far PSF plane (when sensor.laser_halo): its FFT buffers and float64 integral image
  mask pool    data.masks: every further pool member's kept halo (its float64 integral image; shared between the
               pixel scales of one mask) and PSF spectra
  base         the interpreter and its libraries

Calibrated on the peak resident memory of real CPU baseline runs (preset cpu, 2 steps, /usr/bin/time -v):
batch 4 peaked at 2.27 GiB (estimate 2.94), batch 16 at 5.92 GiB (estimate 7.15): 0.30 GiB more per sample
where the hook counts 0.35. A run is refused only when the estimate exceeds what is available now
(MemAvailable on Linux; free device memory on CUDA).
"""
from __future__ import annotations

import logging
import os

import torch

from codesign.errors import ConfigError

log = logging.getLogger("codesign.memory")

ACTIVATION_FACTOR = 1.0
SIMULATION_BYTES = 64  # per sample and FFT-plane pixel
BASE_BYTES = 2**29  # the interpreter, torch and the rest of the process
HALO_BYTES = 40  # per far-plane pixel: complex64 pupil plane and spectrum, float32 PSF, float64 integral image
KEPT_HALO_BYTES = 10  # per far-plane pixel of a pool member's kept halo: its float64 integral image, slack (measured)
KEPT_OPTICS_BYTES = 2**24  # a pool member's window PSF, kernels and their float64 spectra
GIB = 2**30


def available_bytes(device: torch.device) -> tuple[int | None, str]:
    """(bytes free now, where that number comes from); None when the platform does not say."""
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return int(free), f"free memory of {torch.cuda.get_device_name(device)}"
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "MemAvailable in /proc/meminfo"
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "available physical pages"
    except (ValueError, OSError, AttributeError):
        return None, "unknown"


def saved_bytes_per_sample(model, padded: int) -> int:
    """Bytes the restorer's forward saves for backward on one (1, 1, padded, padded) sample (CPU, float32)."""
    saved = 0

    def pack(t: torch.Tensor) -> torch.Tensor:
        nonlocal saved
        saved += t.numel() * t.element_size()
        return t

    x = torch.zeros(1, 1, padded, padded)
    otf = torch.ones(padded, padded // 2 + 1, dtype=torch.complex64)
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t), torch.enable_grad():
        model.restore(x, otf, model.generators())
    return saved


def training_estimate(model, camera, batch: int, ema: bool = False, pool: list | None = None) -> dict:
    """The estimate (bytes per part and total) of a training run of ``model`` on ``camera``'s images (and on those
    of the ``pool`` cameras, data.masks: each keeps its optics, and its own halo unless it shares another's)."""
    params = sum(p.numel() for m in model.generators() + model.critics() for p in m.parameters())
    parts = {
        "parameters": params * (5 if ema else 4) * 4,
        "activations": int(batch * saved_bytes_per_sample(model, camera.padded_size) * ACTIVATION_FACTOR),
        "simulation": batch * camera.simulator.coarse.n_fft ** 2 * SIMULATION_BYTES,
        "base": BASE_BYTES,
    }
    pool = pool or []
    if camera.halo_on:  # sensor.laser_halo, and no measured PSF (which has no halo)
        parts["laser_halo"] = _far_n(camera) ** 2 * HALO_BYTES
    if pool:
        kept = sum(_far_n(c) ** 2 * KEPT_HALO_BYTES for c in pool if c.halo_on and c.halo_donor is None)
        parts["mask_pool"] = kept + len(pool) * KEPT_OPTICS_BYTES
    return {**parts, "total": sum(parts.values())}


def _far_n(camera) -> int:
    """Samples per side of the far PSF plane of ``camera``'s halo (its sensor's reach)."""
    from codesign.optics.far_field import far_spec

    return far_spec(camera.system.spec, camera.sensor.side_m).focal_n


def check_training_fits(model, data, spec, device, task: str) -> dict:
    """``check_fits`` of a training run: this process's share of data.batch_size (the global batch)."""
    batch = data.sampler.batch_size
    share = -(-batch // data.dist.world)
    pool = getattr(data, "pool", None)
    return check_fits(training_estimate(model, data.camera, share, bool(spec.ema), pool.cameras if pool else None),
                      device, f"+experiment={task} (batch {share} per process)", batch)


def check_fits(estimate: dict, device: torch.device, what: str, batch: int) -> dict:
    """Log the estimate; ConfigError naming the keys to lower when it exceeds the memory available now."""
    free, source = available_bytes(device)
    shown = ", ".join(f"{k} {v / GIB:.2f}" for k, v in estimate.items() if k != "total")
    log.info("memory estimate of %s: %.2f GiB (%s GiB); available %s", what, estimate["total"] / GIB, shown,
             f"{free / GIB:.1f} GiB ({source})" if free is not None else "unknown")
    if free is not None and estimate["total"] > free:
        raise ConfigError("data.batch_size", batch,
                          f"{what} needs about {estimate['total'] / GIB:.1f} GiB ({shown} GiB) but "
                          f"{free / GIB:.1f} GiB are available ({source}): lower data.batch_size (activations and "
                          f"simulation grow with it), data.padded_size / data.image_size, or model.size")
    return {"memory_estimate_gib": estimate["total"] / GIB}  # what was available is in the log (it varies)
