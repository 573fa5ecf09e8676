"""``+experiment=restore input=PATH checkpoint=PATH``: restore real or simulated 16-bit sensor captures.

Input: one 16-bit PNG / TIFF, or a folder of them, holding sensor counts (DN) at the checkpoint's network
resolution (data.image_size square, e.g. the captures +experiment=simulate writes). Every file is checked
(size, single channel, 16-bit integer samples, counts within the sensor's bit depth) before any restoration
starts. Output: restored_<name>.png (16-bit, radiance 0..1 -> 0..65535) in the run dir, and metrics.json.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from codesign.camera import build_camera, field_of_view, with_measured_psf
from codesign.config.runtime import explicit_keys, mask_typed, with_typed_mask
from codesign.design.check import camera_sampling_report
from codesign.design.measured_merit import measured_psf_report
from codesign.errors import ConfigError
from codesign.io import files as io
from codesign.io.captures import read_counts, save_png16
from codesign.io.tensorboard import log_summary, open_writer, tensorboard_enabled
from codesign.train.checkpoint import nonfinite_summary, stored_config_error
from codesign.train.resume import apply_checkpoint_mask, load_trained
from codesign.experiments.protocol import Experiment

log = logging.getLogger("codesign.restore")


EXPERIMENT = Experiment(
    summary="restore 16-bit sensor captures with a trained checkpoint",
    first_work="build_camera().frozen_optics",
    root_keys=("input", "checkpoint"),
    reads=(),  # optics, sensor, model and data are the checkpoint's (but a measured PSF, optics.psf_*, typed here)
    outputs=("metrics.json",),
    measured_psf=True,
)

SUFFIXES = (".png", ".tif", ".tiff")


def input_files(path) -> list[Path]:
    if not path:
        raise ConfigError("input", path, "give a 16-bit PNG/TIFF sensor image or a folder of them: input=PATH")
    p = Path(str(path)).expanduser()
    if p.is_file():
        if p.suffix.lower() not in SUFFIXES:
            raise ConfigError("input", str(path), f"must be a {', '.join(SUFFIXES)} file")
        return [p]
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in SUFFIXES and not f.name.startswith("."))
        if not files:
            raise ConfigError("input", str(path), f"folder holds no {', '.join(SUFFIXES)} files")
        stems = [f.stem for f in files]
        clash = sorted({s for s in stems if stems.count(s) > 1})
        if clash:
            raise ConfigError("input", str(path), f"holds files that would write the same output "
                              f"restored_{clash[0]}.png: rename one of {[f.name for f in files if f.stem == clash[0]]}")
        return files
    raise ConfigError("input", str(path), "no such file or folder")


def validate(files: list[Path], size: int, saturation_dn: float, padded: int | None = None) -> list[np.ndarray]:
    """The counts of every file, each checked (size, range) before any is used; ``padded``: the checkpoint's
    data.padded_size, named in the hint of a size error."""
    images = []
    for f in files:
        arr = read_counts(f)
        if arr.shape != (size, size):
            raise ConfigError("input", str(f), f"is {arr.shape[1]} x {arr.shape[0]} px: the checkpoint's network "
                              f"resolution is {size} x {size} (data.image_size)" + (
                                  f"; simulate captures at that size with +experiment=simulate data.image_size="
                                  f"{size} data.padded_size={padded}" if padded else ""))
        if arr.max() > saturation_dn:
            raise ConfigError("input", str(f), f"has counts up to {arr.max():.0f} DN, above the sensor's "
                              f"{saturation_dn:.0f} DN (sensor.bit_depth)")
        images.append(arr)
    return images


def check_finite_output(restored: torch.Tensor, f: Path, path) -> None:
    """A restoration holding NaN or inf (finite weights that overflow on this capture) stops the run, naming the
    checkpoint and the capture: a 16-bit PNG would store NaN as 0, a black image read as a result."""
    bad = nonfinite_summary(restored)
    if bad:
        raise ConfigError("checkpoint", str(path), f"its network restores input {f} to {bad} (not finite): its "
                          f"weights are finite but the network does not compute finite images; nothing written")


def run(cfg, run_dir: Path, device: torch.device) -> float:
    files = input_files(cfg.get("input"))
    if not cfg.get("checkpoint"):
        raise ConfigError("checkpoint", cfg.get("checkpoint"), "give the trained model: checkpoint=PATH")
    model, generators, ckpt_cfg, state = load_trained(cfg.checkpoint, device)
    typed = explicit_keys()
    ckpt_cfg = with_measured_psf(ckpt_cfg, cfg, typed)  # the Wiener stage's OTF then is the measured PSF's
    ckpt_cfg = with_typed_mask(ckpt_cfg, cfg, typed)  # the captures came through this mask (a pool-trained restorer)
    try:
        camera = build_camera(ckpt_cfg, device, torch.float32)
    except ConfigError as err:  # the checkpoint's own settings: say so, not just the key
        if err.key.startswith("optics.psf_"):  # a measured PSF's file (this run's, or the checkpoint's own)
            raise
        raise stored_config_error("checkpoint", cfg.checkpoint, err) from None
    if not mask_typed(typed):
        apply_checkpoint_mask(camera.mask, state, cfg.checkpoint)
    sensor = camera.sensor
    # every file checked before any work
    images = validate(files, sensor.image_size, sensor.saturation_dn, sensor.padded_size)
    sampling = {**camera_sampling_report(camera, ckpt_cfg, log), **measured_psf_report(camera, ckpt_cfg, log)}
    otf = camera.otf
    n, p = sensor.image_size, sensor.padded_size
    m = (p - n) // 2
    written, restored, t0 = [], [], time.perf_counter()
    with torch.no_grad():
        for f, arr in zip(files, images):
            x = torch.from_numpy(arr / (sensor.gain_dn_per_e * sensor.full_well_e)).float()[None, None]
            x = F.pad(x, (m, p - n - m, m, p - n - m)).to(device)
            b = field_of_view(model.restore(x, otf, generators)["restored"], n)
            check_finite_output(b, f, cfg.checkpoint)
            restored.append(b.clamp(0, 1)[0, 0].cpu().numpy())
    # written only once every image restored finite: a bad one never leaves a folder of half the outputs
    for f, b in zip(files, restored):
        out = run_dir / f"restored_{f.stem}.png"
        save_png16(out, b, scale=65535.0)
        written.append(out.name)
    seconds = (time.perf_counter() - t0) / len(files)
    metrics = {**sampling, "inputs": [str(f) for f in files], "outputs": written, "seconds_per_image": seconds,
               "checkpoint": str(cfg.checkpoint), "device": str(device), "image_size": n, "padded_size": p}
    io.write_json(run_dir / "metrics.json", metrics)
    writer = open_writer(run_dir, tensorboard_enabled(cfg))
    if writer is not None:
        for f, arr, b in zip(files, images, restored):
            writer.add_image(f"input/{f.stem}", (arr / sensor.saturation_dn).astype(np.float32)[None], 0)
            writer.add_image(f"restored/{f.stem}", b[None], 0)
    log_summary(writer, {"checkpoint": str(cfg.checkpoint)}, metrics)
    log.info("restored %d image(s) into %s (%.3f s/image)", len(files), run_dir, seconds)
    return seconds
