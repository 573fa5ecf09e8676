"""``+experiment=restore input=PATH checkpoint=PATH``: restore real or simulated 16-bit sensor captures.

Input: one 16-bit PNG / TIFF, or a folder of them, holding sensor counts (DN) of a sensor of the configured pitch
(sensor.pixel_pitch_m, the checkpoint's sensor). A network that takes any size (model=wiener_naf, the shipped
``checkpoint=pretrained``) restores a capture of any size and aspect: binned to the pixel scale it works at
(``restore.bin``: sensor pixels per network pixel; default its finest trained scale, e.g. 2532 px -> 256), or at the
scale asked (``restore.bin=1``: full resolution), through the PSF of the run's mask and optics (``mask=...``, or
a measured PSF ``optics.psf_file``) at that pixel, its decoder tiled where the canvas is large (``restore.tile``),
with a progress line per tile (codesign/models/capture.py). The SGAN checkpoints restore captures of exactly their
network resolution (data.image_size square, e.g. the captures +experiment=simulate writes). Every file is checked
(single channel, 16-bit integer samples, counts within the sensor's bit depth, size) before any restoration starts.
Output: restored_<name>.png (16-bit, 0..1 of the full well at the sensor's exposure -> 0..65535; an SGAN: the scene
radiance) in the run dir, and metrics.json.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from codesign.camera import build_camera, field_of_view
from codesign.experiments.typed_values import log_typed_values
from codesign.config.runtime import explicit_keys, mask_typed, tensorboard_enabled, to_container, with_typed_mask
from codesign.errors import ConfigError, special_file
from codesign.io import files as io
from codesign.io.captures import read_counts, saturation_note, save_png16
from codesign.io.tensorboard import log_summary, open_writer
from codesign.models.capture import RestoreSpec, binned_shape, capture_factor, capture_geometry, restore_capture
from codesign.train.checkpoint import nonfinite_summary, stored_config_error
from codesign.train.resume import apply_checkpoint_mask, load_trained
from codesign.experiments.specs import camera_reports, with_measured_psf
from codesign.experiments.protocol import Experiment

log = logging.getLogger("codesign.restore")


EXPERIMENT = Experiment(
    summary="restore 16-bit sensor captures with a trained checkpoint",
    first_work="build_camera().frozen_optics",
    root_keys=("input", "checkpoint", "restore"),
    reads=(),  # optics, sensor, model and data are the checkpoint's (but a measured PSF, optics.psf_*, typed here)
    outputs=("metrics.json",),
    measured_psf=True,
)

SUFFIXES = (".png", ".tif", ".tiff")


def input_files(path) -> list[Path]:
    """The captures ``input=PATH`` names: the file itself, or a folder's PNG/TIFF files sorted by name (hidden ones
    skipped); a ConfigError for a missing path, another suffix, an empty folder or two files of one output name."""
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
        skipped = sorted(f.name for f in p.iterdir() if f not in files and not f.name.startswith("."))
        if skipped:  # a capture saved under another suffix would otherwise go missing without a word
            log.warning("input = %r: skipped %d entry(ies) that are no %s capture: %s", str(path), len(skipped),
                        "/".join(SUFFIXES), ", ".join(skipped[:8]) + (" and more" if len(skipped) > 8 else ""))
        stems = [f.stem for f in files]
        clash = sorted({s for s in stems if stems.count(s) > 1})
        if clash:
            raise ConfigError("input", str(path), f"holds files that would write the same output "
                              f"restored_{clash[0]}.png: rename one of {[f.name for f in files if f.stem == clash[0]]}")
        return files
    kind = special_file(p)  # a device or a pipe is there: never opened (a pipe would block), named as what it is
    raise ConfigError("input", str(path), f"is {kind}, not a regular file: give a 16-bit PNG/TIFF capture or a "
                      f"folder of them" if kind else "no such file or folder")


def validate(files: list[Path], size: int | None, saturation_dn: float, padded: int | None = None) -> list[np.ndarray]:
    """The counts of every file, each checked (range; ``size``: the square side a fixed-size network needs, None
    for a network that takes any size) before any is used; ``padded``: the checkpoint's data.padded_size, named in
    the hint of a size error."""
    images = []
    for f in files:
        arr = read_counts(f)
        if size is not None and arr.shape != (size, size):
            raise ConfigError("input", str(f), f"is {arr.shape[1]} x {arr.shape[0]} px: the checkpoint's network "
                              f"resolution is {size} x {size} (data.image_size)" + (
                                  f"; simulate captures at that size with +experiment=simulate data.image_size="
                                  f"{size} data.padded_size={padded}" if padded else "") +
                              "; a network that takes any size restores any capture (checkpoint=pretrained)")
        if arr.max() > saturation_dn:
            raise ConfigError("input", str(f), f"has counts up to {arr.max():.0f} DN, above the sensor's "
                              f"{saturation_dn:.0f} DN (sensor.bit_depth)")
        note = saturation_note(arr, saturation_dn)
        if note:
            log.warning("input = %r: %s", str(f), note)
        images.append(arr)
    return images


def working_bin(spec: RestoreSpec, ckpt_cfg, images: list[np.ndarray]) -> float:
    """Capture pixels per network pixel (restore.bin or the checkpoint's working scale, over restore.input_bin);
    checked so that every capture keeps >= 8 network pixels a side."""
    factor = capture_factor(spec, ckpt_cfg)
    smallest = min(min(a.shape) for a in images)
    if min(binned_shape((smallest, smallest), factor)) < 8:
        raise ConfigError("restore.bin", spec.bin if spec.bin is not None else round(factor * spec.input_bin, 4),
                          f"leaves the smallest capture ({smallest} px a side) under 8 network pixels: at most "
                          f"{smallest * spec.input_bin / 8:g} sensor pixels per network pixel")
    return factor


def check_finite_output(restored: torch.Tensor, f: Path, path) -> None:
    """A restoration holding NaN or inf (finite weights that overflow on this capture) stops the run, naming the
    checkpoint and the capture: a 16-bit PNG would store NaN as 0, a black image read as a result."""
    bad = nonfinite_summary(restored)
    if bad:
        raise ConfigError("checkpoint", str(path), f"its network restores input {f} to {bad} (not finite): its "
                          f"weights are finite but the network does not compute finite images; nothing written")


def _tile_progress(name: str):
    """A progress line per tile of a large capture (a bar in the log)."""
    def report(done: int, total: int) -> None:
        if total > 1:
            bar = "#" * round(20 * done / total)
            log.info("restore %s: [%-20s] tile %d/%d", name, bar, done, total)
    return report


def restore_any_size(model, generators, camera, images, files, factor: float, spec: RestoreSpec, path):
    """Each capture binned by ``factor`` and restored through the camera's window PSF (codesign/models/capture.py);
    (restored images, per-image facts)."""
    psf = camera.frozen_optics().state.psf
    restored, facts = [], []
    for f, arr in zip(files, images):
        t0 = time.perf_counter()
        pitch = camera.sensor.pixel_pitch_m * spec.input_bin  # the capture's pixel
        geometry = capture_geometry(arr.shape, factor, pitch, camera.optics.focal_extent_m)
        tile = spec.tile_for(geometry)
        out = restore_capture(model, torch.from_numpy(arr), psf, camera.sensor, geometry, generators, tile,
                              _tile_progress(f.name))
        check_finite_output(out, f, path)
        restored.append(out[0].clamp(0, 1).cpu().numpy())
        facts.append({"input": str(f), "input_size": list(arr.shape), "output_size": list(geometry.size),
                      "kernel_px": geometry.kernel, "canvas": list(geometry.canvas), "tile": tile,
                      "seconds": round(time.perf_counter() - t0, 3)})
    return restored, facts


def restore_fixed_size(model, generators, camera, images, files, path):
    """A network of one input size (the SGAN): each capture at data.image_size on its padded grid."""
    sensor, otf = camera.sensor, camera.otf
    n, p = sensor.image_size, sensor.padded_size
    m = (p - n) // 2
    restored = []
    for f, arr in zip(files, images):
        x = torch.from_numpy(arr / (sensor.gain_dn_per_e * sensor.full_well_e)).float()[None, None]
        x = F.pad(x, (m, p - n - m, m, p - n - m)).to(otf.device)
        b = field_of_view(model.restore(x, otf, generators)["restored"], n)
        check_finite_output(b, f, path)
        restored.append(b.clamp(0, 1)[0, 0].cpu().numpy())
    return restored


def warn_other_mask(model, ckpt_cfg, state: dict, cfg, typed: frozenset, path) -> bool:
    """Warn (and return True) when the mask typed here (mask=... / mask.*=...) is not the one the checkpoint's
    network was trained on and the network cannot know it: trained on one mask (no data.masks pool) and not
    conditioned on the mask (Restorer.mask_conditioned: model=wiener_naf takes the mask's OTF as an input). Warned,
    not refused: the captures may well have come through another mask (what typing one says), and restoring them
    with a network trained on another is a legitimate test of how far it carries; but it went unsaid."""
    if not mask_typed(typed) or model.mask_conditioned or OmegaConf.select(ckpt_cfg, "data.masks"):
        return False
    own, here = to_container(ckpt_cfg.get("mask")), to_container(cfg.get("mask"))
    learned = state.get("mask") is not None  # a co-designed checkpoint: its network learned its learned mask
    if own == here and not learned:
        return False
    trained = "its learned (co-designed) mask" if learned else f"a {own.get('kind')} mask"
    log.warning("checkpoint %s: its network (model.kind=%s) was trained on %s only (no data.masks pool) and is not "
                "conditioned on the mask; this run restores through the typed mask=%s%s, which the network never saw: "
                "expect worse restorations (omit mask=... to restore through the checkpoint's own mask, or use a "
                "restorer for any mask: checkpoint=pretrained, model=wiener_naf)", path, model.kind, trained,
                here.get("kind"), "" if here.get("kind") != own.get("kind") else " (other settings)")
    return True


def run(cfg, run_dir: Path, device: torch.device) -> float:
    """Check the inputs and the checkpoint, build its camera (with the typed mask or measured PSF), restore every
    capture, then write the restored PNGs (only once all are finite), metrics.json and TensorBoard images."""
    files = input_files(cfg.get("input"))
    if not cfg.get("checkpoint"):
        raise ConfigError("checkpoint", cfg.get("checkpoint"), "give the trained model: checkpoint=PATH")
    spec = RestoreSpec.from_config(to_container(cfg.get("restore")) or {})
    model, generators, ckpt_cfg, state = load_trained(cfg.checkpoint, device)
    typed = explicit_keys()
    warn_other_mask(model, ckpt_cfg, state, cfg, typed, cfg.checkpoint)
    ckpt_cfg = with_measured_psf(ckpt_cfg, cfg, typed)  # the Wiener stage's OTF then is the measured PSF's
    ckpt_cfg = with_typed_mask(ckpt_cfg, cfg, typed)  # the captures came through this mask (a pool-trained restorer)
    log_typed_values(log, "restore", cfg, ckpt_cfg, typed)
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
    fixed = None if model.any_size else sensor.image_size
    images = validate(files, fixed, sensor.saturation_dn, sensor.padded_size)
    factor = working_bin(spec, ckpt_cfg, images) if model.any_size else sensor.bin_factor
    for key, value, default in (("restore.bin", spec.bin, None), ("restore.input_bin", spec.input_bin, 1.0)):
        if value != default and not model.any_size:
            raise ConfigError(key, value, f"is for networks that take any size; this checkpoint's ({model.kind}) "
                              f"restores captures of {sensor.image_size} px only (leave {key} at its default)")
    sampling = camera_reports(camera, ckpt_cfg, log)
    t0 = time.perf_counter()
    with torch.no_grad():
        if model.any_size:
            restored, facts = restore_any_size(model, generators, camera, images, files, factor, spec,
                                               cfg.checkpoint)
        else:
            restored, facts = restore_fixed_size(model, generators, camera, images, files, cfg.checkpoint), []
    seconds = (time.perf_counter() - t0) / len(files)
    # written only once every image restored finite: a bad one never leaves a folder of half the outputs
    written = []
    for f, b in zip(files, restored):
        out = run_dir / f"restored_{f.stem}.png"
        save_png16(out, b, scale=65535.0)
        written.append(out.name)
    metrics = {**sampling, "inputs": [str(f) for f in files], "outputs": written, "seconds_per_image": seconds,
               "checkpoint": str(cfg.checkpoint), "device": str(device), "image_size": sensor.image_size,
               "padded_size": sensor.padded_size, "bin": factor * spec.input_bin, "input_bin": spec.input_bin,
               "network_pitch_m": sensor.pixel_pitch_m * factor * spec.input_bin,
               "captures": facts}
    io.write_json(run_dir / "metrics.json", metrics)
    writer = open_writer(run_dir, tensorboard_enabled(cfg))
    if writer is not None:
        for f, arr, b in zip(files, images, restored):
            writer.add_image(f"input/{f.stem}", (arr / sensor.saturation_dn).astype(np.float32)[None], 0)
            writer.add_image(f"restored/{f.stem}", b[None], 0)
    log_summary(writer, {"checkpoint": str(cfg.checkpoint)}, metrics)
    log.info("restored %d image(s) into %s (%.3f s/image, %.4g sensor px per network px)", len(files), run_dir,
             seconds, factor)
    return seconds
