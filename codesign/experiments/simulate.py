"""``+experiment=simulate``: example sensor images across laser strengths, 16-bit captures, and metrics.

The captures go into their own folder, ``captures/``, so that it can be handed to the restorer as it is
(``+experiment=restore input=<run>/captures checkpoint=...``; simulate at the checkpoint's data.image_size, e.g.
preset=cpu for a CPU baseline)."""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from codesign.camera import build_camera
from codesign.config.runtime import check_seed, resolve_dtype, tensorboard_enabled, to_container
from codesign.data.paramconfig import ParamConfig
from codesign.data.params import alpha_tag, fixed_scene_params, sample_scene_params
from codesign.data.scenes import build_scene_source
from codesign.data.simulate_spec import SimulateSpec
from codesign.design.check import camera_sampling_report
from codesign.design.measured_merit import measured_psf_figure, measured_psf_report
from codesign.io import files as io
from codesign.io.captures import save_png16
from codesign.io.plots import plt
from codesign.io.tensorboard import log_summary, open_writer
from codesign.experiments.specs import metrics_spec
from codesign.experiments.protocol import Experiment

log = logging.getLogger("codesign.simulate")


EXPERIMENT = Experiment(
    summary="dazzled 16-bit sensor captures of test scenes at the paper's laser strengths",
    first_work="build_camera().frozen_optics",
    root_keys=("precision", "simulate"),
    reads=("optics", "material", "mask", "sensor", "data", "metrics"),
    outputs=("metrics.json", "sensor_grid_linear.png", "sensor_grid_log.png", "measured_psf.png"),  # the last: with
    # a measured PSF only
    measured_psf=True,
    smoke={"simulate.scenes": 1, "simulate.laser_strengths": [0, 1.0e6], "simulate.timing_repeats": 1},
)

CAPTURES = "captures"  # the 16-bit sensor captures alone: a folder +experiment=restore takes as input=DIR

def _grid_figure(images: np.ndarray, rows: list[str], cols: list[float], log_view: bool, full_scale: float):
    """The simulated captures (rows: scenes, columns: laser strengths alpha_l) on one grey scale in DN, linear
    (0 .. full scale G e_sat) or log10, with its colour bar."""
    nr, nc = images.shape[:2]
    # log view: from the darkest 1% of the laser-free captures (read offset + dim scene) to full scale, so that
    # faint laser structure (alpha_l = 10, 100) stands out
    log_lo = float(np.log10(max(np.percentile(images[:, 0], 1), 1.0)))
    fig, axes = plt.subplots(nr, nc, figsize=(1.9 * nc + 1.3, 2.0 * nr + 0.5), squeeze=False, layout="constrained")
    im = None
    for i in range(nr):
        for j in range(nc):
            ax = axes[i][j]
            img = images[i, j]
            if log_view:
                im = ax.imshow(np.log10(np.maximum(img, 1.0)), cmap="gray", vmin=log_lo, vmax=np.log10(full_scale))
            else:
                im = ax.imshow(img, cmap="gray", vmin=0, vmax=full_scale)
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(f"alpha_l = {alpha_tag(cols[j])}", fontsize=8)
            if j == 0:
                ax.set_ylabel(rows[i], fontsize=8)
    bar = fig.colorbar(im, ax=axes, shrink=0.9)
    bar.set_label("log10 counts [DN]" if log_view else "counts [DN]", fontsize=8)
    bar.ax.tick_params(labelsize=7)
    fig.suptitle(("log10 counts" if log_view else "counts (linear)") + f" of the simulated sensor, full scale G e_sat "
                 f"= {full_scale:.4g} DN;\nrows: scenes, columns: laser strength alpha_l", fontsize=8)
    return fig


def warn_laser_off_sensor(angle: list[float], focal_length_m: float, side_m: float, halo: bool) -> bool:
    """Warn when the laser's spot (at f * angle from the sensor centre) lands beyond the sensor; True then. The
    captures then hold its halo alone (sensor.laser_halo), or nothing of it: no alpha_l column differs."""
    spot = [focal_length_m * a for a in angle]
    if max(abs(x) for x in spot) <= side_m / 2:
        return False
    log.warning("simulate.laser_angle_rad = [%g, %g]: the laser's spot lands (%.3g, %.3g) mm from the sensor's centre, "
                "beyond the sensor (%.3g mm square): %s", angle[0], angle[1], spot[0] * 1e3, spot[1] * 1e3,
                side_m * 1e3, "only its halo reaches the captures (sensor.laser_halo)" if halo else
                "nothing of the laser reaches the captures (sensor.laser_halo is off)")
    return True


def run(cfg: DictConfig, run_dir: Path, device: torch.device) -> float:
    """Test scenes through the configured camera at each of simulate.laser_strengths: the 16-bit captures (in
    captures/), their grid figures, example arrays, the simulator's throughput on a training-like batch and
    metrics.json; returns the seconds per simulated image. Steps: build, simulate, time, report."""
    s = SimulateSpec.from_config(to_container(cfg.get("simulate")) or {})
    dtype = resolve_dtype("precision", cfg.get("precision"))
    camera, names, scenes, reports = _build(cfg, s, device, dtype)
    optics = camera.frozen_optics()
    seed = check_seed(cfg)
    with torch.no_grad():
        grid, metrics = _simulate(run_dir, camera.simulator, optics, scenes, names, s, seed, device, dtype)
        seconds, batch = _throughput(cfg, camera.simulator, optics, scenes, s.timing_repeats, seed, device, dtype)
    _report(cfg, run_dir, camera, optics.state, grid, names, s.laser_strengths, metrics, reports, dtype, device,
            {"seconds_per_image": seconds, "images_per_second": 1.0 / seconds, "batch_size": batch})
    log.info("scenes %s; saturated fraction per alpha_l: %s; %.4f s/image (%.1f images/s, batch %d, %s path)",
             ", ".join(names), ", ".join(f"{alpha_tag(a)}: {metrics[f'saturated_fraction_alpha_l_{alpha_tag(a)}']:.4f}"
                                         for a in s.laser_strengths), seconds, 1 / seconds, batch,
             camera.simulator.sensor.path)
    return seconds


def _readable_scenes(source, count: int, size: int) -> list[str]:
    """The first ``count`` test scenes (then any scenes) that decode: a file that fails (non-finite pixels, a
    truncated file: probed as readable, found corrupt only when decoded) is skipped with the SceneLoadWarning every
    corrupt file gets (SceneSource drops it from its splits); ConfigError(data.folder) when none is left."""
    from codesign.data.images import UnreadableImage
    from codesign.errors import ConfigError

    names: list[str] = []
    for split in ("test", "all"):
        for name in source.split_names(split):
            if len(names) == count:
                return names
            if name in names:
                continue
            try:
                source.image(name, size)
            except UnreadableImage:
                continue
            names.append(name)
    if not names:
        raise ConfigError(source.key, source.origin, "holds no image that decodes (each was skipped above)")
    return names


def _build(cfg: DictConfig, s: SimulateSpec, device, dtype) -> tuple:
    """The camera, the test scenes (names, tensor) and the reports made before any work (phase sampling, a laser
    beyond the sensor, a measured PSF): (camera, names, scenes, reports)."""
    source = build_scene_source(cfg.data)
    camera = build_camera(cfg, device, dtype)
    sim = camera.simulator
    names = _readable_scenes(source, s.scenes, sim.scene_size)
    scenes = source.fixed_batch(names, sim.scene_size).to(device=device, dtype=dtype)
    log.info("sensor path %s: %d x %d network pixels of %.3g m (bin %.3f), scene crop %d, PSF kernel %d",
             sim.sensor.path, sim.sensor.image_size, sim.sensor.image_size, sim.sensor.coarse_pitch_m,
             sim.sensor.bin_factor, sim.scene_size, sim.coarse.ksize)
    band = metrics_spec(cfg).mtf_band
    sampling = camera_sampling_report(camera, band, log)
    off_sensor = warn_laser_off_sensor(list(s.laser_angle_rad), sim.optics.focal_length_m, sim.sensor.side_m,
                                       camera.halo_on)
    curves: dict = {}
    measured = measured_psf_report(camera, band, log, curves)
    return camera, names, scenes, {"sampling": sampling, "off_sensor": off_sensor, "measured": measured,
                                   "curves": curves}


def _simulate(run_dir: Path, sim, optics, scenes, names: list[str], s: SimulateSpec, seed: int, device,
              dtype) -> tuple[np.ndarray, dict]:
    """The scenes at every laser strength (noise seed ``seed`` + its index): the captures written, the example
    arrays of the last; returns (the captures in DN, (scenes, strengths, H, W); saturation and laser peak per
    strength)."""
    alphas, size = s.laser_strengths, sim.sensor.image_size
    grid = np.zeros((len(names), len(alphas), size, size))
    metrics = {}
    for j, a in enumerate(alphas):
        params = fixed_scene_params(len(names), dtype=dtype, device=device, alpha_l=a,
                                    laser_angle_rad=list(s.laser_angle_rad), **s.params)
        out = sim(scenes, params, optics.state, seed=seed + j, mask_key=optics.key)
        dn = out["sensor_dn"][:, 0].cpu().numpy()
        grid[:, j] = dn
        metrics[f"saturated_fraction_alpha_l_{alpha_tag(a)}"] = float(out["saturated"].float().mean())
        metrics[f"laser_peak_alpha_l_{alpha_tag(a)}"] = float(out["laser"].max())
        for i, name in enumerate(names):
            save_png16(run_dir / CAPTURES / f"sensor_{name}_alpha_l_{alpha_tag(a)}.png", dn[i])
        if j == len(alphas) - 1:
            io.save_npy(run_dir / "example_sensor.npy", out["sensor"][0, 0])
            io.save_npy(run_dir / "example_irradiance_target.npy", out["irradiance"][0, 0])
            io.save_npy(run_dir / "example_scene_target.npy", out["scene"][0, 0])
    return grid, metrics


def _throughput(cfg: DictConfig, sim, optics, scenes, repeats: int, seed: int, device, dtype) -> tuple[float, int]:
    """Seconds per image of the simulator on a training-like batch (random Sec. 6.2 parameters, data.batch_size),
    after one warm-up that fills the kernel cache: (seconds, batch size)."""
    gen = torch.Generator().manual_seed(seed)
    batch = int(cfg.data.batch_size)
    side_m = sim.sensor.side_m
    sp = sample_scene_params(batch, gen, ParamConfig.from_config(cfg.data.params), sensor_width_m=side_m,
                             sensor_height_m=side_m, focal_length_m=sim.optics.focal_length_m)
    sp = sp.to(device, dtype)
    idx = torch.arange(batch) % scenes.shape[0]
    bscenes = scenes[idx]
    sim(bscenes, sp, optics.state, seed=seed, mask_key=optics.key)  # warm-up (fills the kernel cache)
    t0 = time.perf_counter()
    for r in range(repeats):
        sim(bscenes, sp, optics.state, seed=seed + r, mask_key=optics.key)
    return (time.perf_counter() - t0) / (repeats * batch), batch


def _report(cfg: DictConfig, run_dir: Path, camera, state, grid: np.ndarray, names: list[str], alphas, metrics: dict,
            reports: dict, dtype, device, timing: dict) -> None:
    """The grid figures (linear, log), the measured PSF's figure, metrics.json and the TensorBoard events."""
    sim = camera.simulator
    full = sim.sensor.gain_dn_per_e * sim.sensor.full_well_e
    io.save_figure(run_dir / "sensor_grid_linear.png", _grid_figure(grid, names, alphas, False, full))
    io.save_figure(run_dir / "sensor_grid_log.png", _grid_figure(grid, names, alphas, True, full))
    measured = reports["measured"]
    if measured:
        io.save_figure(run_dir / "measured_psf.png", measured_psf_figure(
            reports["curves"], f"measured PSF {Path(measured['measured_psf']).name} against the design "
            f"{camera.mask.kind} mask"))
    metrics.update({**reports["sampling"], **measured, **timing,
                    **_camera_figures(sim, state, reports["off_sensor"], len(names)),
                    "precision": str(dtype).replace("torch.", ""), "device": str(device),
                    "threads": torch.get_num_threads()})
    io.write_json(run_dir / "metrics.json", metrics)
    writer = open_writer(run_dir, tensorboard_enabled(cfg))
    if writer is not None:
        for j, a in enumerate(alphas):  # log10 counts, full scale = 1: the laser structure stays visible
            img = np.log10(np.maximum(grid[:, j], 1.0))[:, None] / np.log10(full)
            writer.add_images(f"sensor_log10/alpha_l_{alpha_tag(a)}", img.astype(np.float32), 0)
    log_summary(writer, {"sensor_path": sim.sensor.path, "image_size": sim.sensor.image_size}, metrics)


def _camera_figures(sim, state, off_sensor: bool, scenes: int) -> dict:
    """What metrics.json records of the camera: its sampled LSR (at the design line and the laser's), BSR, window
    energy, the sensor's geometry and saturation irradiance [W/m^2]."""
    lsr = float(state.psf.max()) / state.uncoded_peak
    laser = state.laser or state  # the laser's own PSF when it shines at another line than the scene
    bsr_window = float(state.psf.sum()) / state.uncoded_energy
    return {
        "sensor_path": sim.sensor.path, "lsr_sampled": lsr, "laser_off_sensor": off_sensor,
        "laser_wavelength_m": sim.sensor.wavelength_laser_m,
        "lsr_sampled_laser_line": float(laser.psf.max()) / laser.uncoded_peak,
        # uniform-background ratio of the simulated image: 1 with the out-of-window veil (energy conservation),
        # else the window's (sum h / sum h0); the window's value is always reported
        "bsr": 1.0 if sim.sensor.background_veil else bsr_window,
        "bsr_window": bsr_window, "window_energy": float(state.psf.sum()),
        "background_veil": sim.sensor.background_veil,
        "image_size": sim.sensor.image_size, "padded_size": sim.sensor.padded_size,
        "network_pixel_pitch_m": sim.sensor.coarse_pitch_m, "sensor_resolution": sim.sensor.resolution,
        "scene_size": sim.scene_size, "psf_kernel_size": sim.coarse.ksize, "scenes": scenes,
        "saturation_irradiance_w_m2": sim.sensor.saturation_irradiance(sim.sensor.wavelength_laser_m),
    }
