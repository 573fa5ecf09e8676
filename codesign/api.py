"""The stable Python API: ``from codesign import compose, camera, psf_and_lsr, sensor_image, ...``.

Thin wrappers over the library and the experiments, so that a script needs one import and no knowledge of the
package layout. Like the entry point (codesign/__main__.py) this module sits above every package (it may run
the experiments); nothing in the library imports it. Units are SI throughout (metres, radians); images are
sensor counts (DN) or radiance in [0, 1] as stated. docs/api.md is the reference page.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any, Mapping

import torch
from omegaconf import DictConfig, OmegaConf, open_dict

import codesign.experiments as _experiments
from codesign.experiments import rundir
from codesign.experiments.runlock import release_lock
from codesign.experiments.specs import metrics_spec
from codesign.camera import Camera, build_camera as _camera_of
from codesign.config import CONF_DIR
from codesign.config.runtime import apply_debug_overrides, command_line_keys, renamed_key_error, to_container
from codesign.data.scenes import build_scene_source
from codesign.data.params import alpha_tag, fixed_scene_params
from codesign.data.simulate_spec import SimulateSpec
from codesign.design.merit import evaluate_mask, published_reference
from codesign.errors import ConfigError, require_number
from codesign.optics import OpticalSystem, OpticsSpec, build_mask as _build_mask
from codesign.optics.grid import PupilGrid
from codesign.optics.masks import Mask
from codesign.train.checkpoint import PRETRAINED, load_checkpoint
# the arguments' checks (codesign/api_checks.py): each as the command line checks the key it stands for
from codesign import api_checks as checks
from codesign.api_checks import check_alpha as _check_alpha, check_cfg as _check_cfg, check_kind as _check_kind, \
    check_seed as _check_seed


__all__ = ["compose", "build_camera", "optical_system", "build_mask", "configured_mask", "published_mask",
           "psf_and_lsr", "scene_names", "sensor_image", "run", "checkpoint_config", "restore", "restore_image",
           "quality", "mask_search", "train_restorer", "OpticsSpec", "OpticalSystem", "Camera", "Mask", "ConfigError",
           "alpha_tag", "CONF_DIR"]


def compose(*overrides: str, experiment: str | None = None) -> DictConfig:
    """The composed configuration of ``python -m codesign [+experiment=NAME] OVERRIDES...``, processed as the entry
    point processes it: renamed keys refused, an experiment's unknown root keys refused, and ``debug=smoke`` (any
    ``debug=...``) applied, with the keys typed here left as typed (Hydra's compose API alone skips the shrink).

    overrides: Hydra overrides as on the command line, e.g. ``"mask=spline"``, ``"optics.focal_n=160"``,
    ``"debug=smoke"`` (values in the config's SI units: metres, radians). experiment: an experiment name (psf,
    simulate, baseline, joint, mask_search, restore, evaluate, export, tolerance), same as ``+experiment=NAME``.
    Without one, debug=smoke shrinks every key it names (no experiment's own shrink). Returns an OmegaConf
    DictConfig. Raises ConfigError on a renamed or unknown key, hydra's errors on a bad override.
    """
    from hydra import compose as hydra_compose, initialize_config_dir

    args = checks.check_overrides("compose", overrides, experiment=experiment is not None)
    if experiment is not None:
        args.append(f"+experiment={checks.check_experiment('compose experiment', experiment)}")
    problem = renamed_key_error(args)
    if problem:
        raise ConfigError(problem.split(" ", 1)[0], None, problem)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = hydra_compose("config", overrides=args)
    typed = command_line_keys([a for a in args if "=" in a])
    if cfg.get("task") is not None:
        _experiments.check_root_keys(cfg, cfg.task)
        _experiments.apply_debug(cfg, typed)  # the entry point's shrink (codesign/experiments/__init__.py)
    else:
        apply_debug_overrides(cfg, typed)
    return cfg


# what a mask argument takes, as a message says it
MASK = "a Mask (codesign.published_mask(), configured_mask(cfg), build_mask(...))"
SYSTEM = "an OpticalSystem (codesign.optical_system(cfg))"


def _config(cfg: DictConfig | None) -> DictConfig:
    return compose() if cfg is None else cfg


def build_camera(cfg: DictConfig | None = None, device: str | torch.device = "cpu",
                 dtype: torch.dtype = torch.float32, mask: Mask | None = None) -> Camera:
    """The Camera (optical system, frozen mask, sensor simulator) of ``cfg`` (default: ``compose()``, the default
    optics and the published five half-ring mask); ``mask``: image through this Mask instead of the configured one
    (e.g. a search's design; one built on another pupil grid is sampled onto the camera's). ``cam.frozen_optics()``
    holds the PSF state; ``cam(scenes, params, seed)`` simulates a batch (scenes: (N, 1, S, S) radiance in [0, 1]
    with S = camera.scene_size; params: a SceneParams, e.g. from fixed_scene_params)."""
    _check_cfg("build_camera cfg", cfg)
    _check_kind("build_camera mask", mask, Mask, MASK)
    cam = _camera_of(_config(cfg), checks.check_device("build_camera device", device), dtype)
    cam.check_padding()  # data.padded_size against the PSF kernel, as every experiment that simulates checks it
    if mask is not None:
        cam.use_mask(_on_system_grid(mask, cam.system))
    return cam


def optical_system(cfg: DictConfig | None = None, device: str | torch.device = "cpu",
                   dtype: torch.dtype = torch.float32) -> OpticalSystem:
    """The OpticalSystem (pupil grid, propagator) of ``cfg.optics`` (default: the default optics: 633 nm, f and
    aperture in metres as in conf / OpticsSpec). ``system.psf(mask.phase())`` is the PSF on the focal window."""
    _check_cfg("optical_system cfg", cfg)
    device = checks.check_device("optical_system device", device)
    spec = OpticsSpec.from_config(to_container(_config(cfg).optics))
    return OpticalSystem(spec, dtype=dtype, device=device)


def configured_mask(cfg: DictConfig | None = None, system: OpticalSystem | None = None) -> Mask:
    """The configured mask (``cfg.mask``: mask=<family>, mask.init=PATH) on ``system``'s pupil grid (default:
    optical_system(cfg)). Its ``phase()`` is the pupil phase in radians."""
    _check_cfg("configured_mask cfg", cfg)
    _check_kind("configured_mask system", system, OpticalSystem, SYSTEM, "None (optical_system(cfg))")
    cfg = _config(cfg)
    system = system or optical_system(cfg)
    return _build_mask(to_container(cfg.mask), system.grid, system.spec.aperture_diameter_m)


def build_mask(mask_cfg: Any = None, grid: PupilGrid | None = None, aperture_diameter_m: float | None = None
               ) -> Mask:
    """A Mask of any family from a plain mapping (the library's codesign.optics.build_mask, its values validated as
    ``mask.*`` keys): ``build_mask({"kind": "spiral", ...}, system.grid, system.spec.aperture_diameter_m)``, the
    grid and aperture [m] of an OpticalSystem (codesign.optical_system(cfg))."""
    takes = "(build_mask({'kind': FAMILY, ...}, system.grid, system.spec.aperture_diameter_m))"
    if not isinstance(mask_cfg, Mapping):
        raise ConfigError("build_mask mask_cfg", checks.Shown(mask_cfg), f"must be a mapping of mask.* settings with "
                          f"its 'kind' {takes}")
    if not isinstance(grid, PupilGrid):
        raise ConfigError("build_mask grid", checks.Shown(grid), f"must be an OpticalSystem's grid {takes}")
    aperture = require_number("build_mask aperture_diameter_m", aperture_diameter_m, lo=0, lo_open=True)
    return _build_mask(mask_cfg, grid, aperture)


def published_mask(system: OpticalSystem | None = None, cfg: DictConfig | None = None) -> Mask:
    """The published five half-ring mask (Peng et al., Sec. 3.1: radii r_n in metres, angles theta_n in radians),
    frozen, on ``system``'s grid under the configured mask conventions: every experiment's baseline."""
    _check_cfg("published_mask cfg", cfg)
    _check_kind("published_mask system", system, OpticalSystem, SYSTEM, "None (optical_system(cfg))")
    cfg = _config(cfg)
    system = system or optical_system(cfg)
    return published_reference(to_container(cfg.mask), system)


def psf_and_lsr(mask: Mask | None = None, system: OpticalSystem | None = None,
                cfg: DictConfig | None = None) -> dict[str, Any]:
    """PSF and figures of merit of a mask, as ``+experiment=psf`` reports them (design.merit.evaluate_mask).

    mask: any Mask (default: the published mask; one built on another pupil grid is sampled onto ``system``'s);
    system: the OpticalSystem (default: optical_system(cfg)).
    Returns a dict: ``psf`` (focal-window tensor, focal_n x focal_n samples of focal_pitch_m metres, in units of
    the pupil's total power per sample), ``psf_uncoded`` (the same without the mask), ``phase`` (rad), ``lsr``
    (laser suppression ratio: the certified continuous PSF peak over the uncoded peak, dimensionless),
    ``lsr_sampled``, ``lsr_smooth`` (the differentiable p-norm LSR), ``bsr``, ``mtf_mean``, ``mtf_min`` (over
    metrics.mtf_band, frequency normalized to the incoherent cutoff), ``psf_energy_in_window`` and the rest of
    evaluate_mask's keys."""
    _check_cfg("psf_and_lsr cfg", cfg)
    _check_kind("psf_and_lsr mask", mask, Mask, MASK, "None (the published mask)")
    _check_kind("psf_and_lsr system", system, OpticalSystem, SYSTEM)
    cfg = _config(cfg)
    system = system or optical_system(cfg)
    mask = mask if mask is not None else published_mask(system, cfg)
    mask = _on_system_grid(mask, system)  # e.g. a design from a coarser search, or a float64 grid's
    ms = metrics_spec(cfg)
    values, arrays = evaluate_mask(system, mask, ms.mtf_band, ms.lsr_p, ms.lsr_grids)
    return {**values, "psf": arrays["psf"], "psf_uncoded": arrays["psf_uncoded"], "phase": arrays["phase"]}


def scene_names(cfg: DictConfig | None = None, split: str | None = None) -> list[str]:
    """The names of the scenes of ``cfg.data`` (default: the built-in scikit-image scenes) in ``split`` ('train',
    'test' or 'all'; None: the test split)."""
    _check_cfg("scene_names cfg", cfg)
    return build_scene_source(_config(cfg).data).split_names(split or "test")


def sensor_image(scene: str | int = 0, alpha_l: float = 1e6, cfg: DictConfig | None = None,
                 cam: Camera | None = None, seed: int | None = None, **params: Any) -> dict[str, torch.Tensor]:
    """One simulated sensor image of a built-in (or cfg.data's) scene at laser strength ``alpha_l``, as
    ``+experiment=simulate`` makes it (same scene source, fixed scene parameters, laser angle).

    scene: a name from scene_names(cfg) or an index into the test split. alpha_l: the laser's strength relative to
    the scene (the paper's alpha_l, dimensionless; 0 = no laser). params: other SceneParams fields (paper's figure
    values by default; laser_angle_rad in radians, default simulate.laser_angle_rad). cam: a Camera of cfg to reuse
    (default: build_camera(cfg)). seed: the noise seed (None: the config's seed). Returns the simulator's outputs for a
    batch of one: ``sensor_dn`` (1, 1, n, n) sensor counts (DN, n = data.image_size), ``saturated`` (1, 1, n, n)
    bool, ``laser`` (1, 1, n, n) the laser's part of the image before noise and digitization (irradiance units); on
    the padded grid (1, 1, p, p), p = data.padded_size, the image centred (codesign.camera.field_of_view crops it):
    ``sensor`` (counts / full scale, 0..1, the network input), ``scene`` (the target radiance, 0..1) and
    ``irradiance`` (the scene through the optics)."""
    _check_cfg("sensor_image cfg", cfg)
    _check_kind("sensor_image cam", cam, Camera, "a Camera (codesign.build_camera(cfg))")
    seed, alpha_l = _check_seed("sensor_image seed", seed), _check_alpha("sensor_image alpha_l", alpha_l)
    cfg = _config(cfg)
    source = build_scene_source(cfg.data)
    checks.check_scene("sensor_image scene", scene, source.split_names("test"), source.split_names("all"))
    fixed = SimulateSpec.from_config(to_container(cfg.get("simulate")) or {})
    values = {**fixed.params, "laser_angle_rad": list(fixed.laser_angle_rad), **params, "alpha_l": alpha_l}
    checks.check_scene_params("sensor_image", values)
    cam = cam or build_camera(cfg)
    sim = cam.simulator
    split = "test" if isinstance(scene, int) and not isinstance(scene, bool) else "all"
    scenes = source.fixed_batch([scene], sim.scene_size, split=split).to(cam.device)
    sp = fixed_scene_params(1, device=cam.device, **values)
    with torch.no_grad():
        return cam(scenes, sp, seed=int(cfg.seed) if seed is None else seed)


def _on_system_grid(mask, system):
    """``mask`` on ``system``'s pupil grid: sampled there by its family (Mask.on_grid) when it was built on another
    grid: another size or pitch (a search on a coarser one), or another precision or device (a float64 grid's mask
    in a float32 system was a RuntimeError)."""
    grid, own = system.grid, mask.grid
    same = (own.n == grid.n and abs(own.pitch - grid.pitch) <= 1e-12 * grid.pitch
            and own.rho.dtype == grid.rho.dtype and own.rho.device == grid.rho.device)
    return mask if same else mask.on_grid(grid, system.spec.aperture_diameter_m)


def _new_run_dir(task: str) -> Path:
    return Path("outputs") / "api" / task / time.strftime("%Y-%m-%d_%H-%M-%S") / f"{time.time_ns() % 10**6:06d}"


def run(experiment: str, *overrides: str, run_dir: str | Path | None = None) -> dict[str, Any]:
    """Run an experiment as ``python -m codesign +experiment=NAME OVERRIDES... hydra.run.dir=RUN_DIR`` does, in
    this process (codesign.experiments.run_experiment: validation, debug shrink, threads, device), and return its
    ``metrics.json`` as a dict, with ``run_dir`` (a Path) added. run_dir: default outputs/api/<NAME>/<time>.
    A configuration error raises ConfigError (its key, value and what is allowed), before any work."""
    checks.check_experiment("run experiment", experiment)
    checks.check_overrides("run", overrides, run=True, experiment=True)
    checks.check_run_dir("run run_dir", run_dir)
    cfg = compose(*overrides, experiment=experiment)
    run_dir = Path(run_dir) if run_dir is not None else _new_run_dir(experiment)
    for note in rundir.guard(run_dir, experiment, "run_dir", cfg):  # the command's guard: lock, refusals
        print(f"codesign: note: {note}", file=sys.stderr)
    with open_dict(cfg):
        cfg.debug = None  # applied by compose (typed keys kept); run_experiment would apply it again over them
    try:
        _experiments.run_experiment(cfg, run_dir, exit_on_error=False)
    finally:
        release_lock(run_dir)  # the folder free again for other processes once this run has ended
    metrics_file = run_dir / "metrics.json"
    metrics = json.loads(metrics_file.read_text()) if metrics_file.is_file() else {}
    return {**metrics, "run_dir": run_dir}


def checkpoint_config(checkpoint: str | Path) -> DictConfig:
    """The configuration a checkpoint.pt was trained with (its optics, mask, sensor, data, model blocks): e.g.
    ``sensor_image(cfg=checkpoint_config(path))`` simulates captures at its network resolution for restore()."""
    checks.check_path("checkpoint_config checkpoint", checkpoint, "'pretrained' or a checkpoint.pt path")
    return OmegaConf.create(load_checkpoint(checkpoint)["config"])


def restore(input: str | Path, checkpoint: str | Path, *overrides: str,
            run_dir: str | Path | None = None) -> dict[str, Any]:
    """Restore 16-bit sensor captures with a trained checkpoint (``+experiment=restore``). input: one 16-bit
    PNG/TIFF of sensor counts (DN) at the checkpoint's data.image_size, or a folder of them; checkpoint:
    ``"pretrained"`` (the shipped restorer for any mask, 96 px: codesign/models/pretrained/README.md) or a
    checkpoint.pt written by baseline / joint. Writes
    restored_<name>.png (radiance 0..1 as 0..65535) into run_dir; returns metrics.json (``outputs``,
    ``seconds_per_image``, ...) with ``run_dir``."""
    checks.check_path("restore input", input, "a 16-bit PNG/TIFF capture or a folder of them")
    checks.check_path("restore checkpoint", checkpoint, "'pretrained' or a checkpoint.pt")
    named = str(checkpoint) in PRETRAINED  # a shipped checkpoint's name stays a name
    return run("restore", f"input={Path(input).resolve()}",
               f"checkpoint={checkpoint if named else Path(checkpoint).resolve()}", *overrides, run_dir=run_dir)


def restore_image(counts, checkpoint: str | Path = "pretrained", mask: Mask | None = None, bin: float | None = None,
                  input_bin: float | None = None, tile: int | None = None, device: str | torch.device = "cpu"
                  ) -> torch.Tensor:
    """Restore one capture held in memory, no files: ``counts`` (H, W) or (C, H, W) sensor counts [DN] of any size
    from a sensor of the checkpoint's pitch (e.g. ``sensor_image(...)["sensor_dn"][0, 0]``), through ``mask`` (any
    Mask, e.g. a search's design, sampled onto the checkpoint's pupil grid; default: the checkpoint's own mask), binned to
    ``bin`` sensor pixels per network pixel (default: the network's finest trained scale; ``input_bin``: sensor
    pixels per capture pixel, None or 1 for a raw capture, sensor.resolution / data.image_size for a capture simulated at
    the network resolution as sensor_image makes them), decoded in tiles of
    ``tile`` px (default: whole up to 1536^2 px). checkpoint: 'pretrained' (the shipped restorer for any mask and
    size) or a checkpoint.pt of a network that takes any size (model=wiener_naf). Returns (h, w) (or (C, h, w))
    at the sensor's exposure, 1 = the full well (as +experiment=restore writes it). Raises ConfigError."""
    from codesign.models.capture import RestoreSpec, capture_factor, capture_geometry, restore_capture
    from codesign.train.resume import apply_checkpoint_mask, load_trained

    _check_kind("restore_image mask", mask, Mask, MASK, "None (the checkpoint's own mask)")
    # checkpoint=None was read as the file 'None' ("no such checkpoint file"): say what the argument takes
    checks.check_path("restore_image checkpoint", checkpoint, "'pretrained' or a checkpoint.pt path")
    given = {} if input_bin is None else {"input_bin": input_bin}  # None: RestoreSpec's default, a raw capture
    spec = RestoreSpec(bin=bin, tile=tile, prefix="restore_image", **given)
    x = checks.check_counts("restore_image counts", counts)
    device = checks.check_device("restore_image device", device)
    model, generators, ckpt_cfg, state = load_trained(checkpoint, device)
    cam = _camera_of(ckpt_cfg, device, torch.float32)
    checks.check_capture_fits("restore_image counts", x, int(ckpt_cfg.get("model", {}).get("channels", 1) or 1),
                              cam.sensor.saturation_dn)
    if mask is None:
        apply_checkpoint_mask(cam.mask, state, checkpoint)
    else:  # on the checkpoint's pupil grid (sampled onto it by its family when it was designed on another)
        cam.use_mask(_on_system_grid(mask, cam.system))
    psf = cam.frozen_optics().state.psf
    factor = capture_factor(spec, ckpt_cfg)
    geometry = capture_geometry(tuple(x.shape[-2:]), factor, cam.sensor.pixel_pitch_m * spec.input_bin,
                                cam.optics.focal_extent_m)
    out = restore_capture(model, x, psf, cam.sensor, geometry, generators, spec.tile_for(geometry))
    return out[0] if x.dim() == 2 else out


def quality(restored: torch.Tensor, scene: torch.Tensor) -> dict[str, float]:
    """How close ``restored`` is to ``scene`` (both (H, W) or (N, 1, H, W), radiance in [0, 1], at least 11 px a
    side), as the evaluation scores: ``psnr`` and ``ssim`` as they are, ``psnr_matched`` and ``ssim_matched`` after
    the least-squares gain and offset (the sensor cannot tell the scene's level: alpha_b is unknown), dB and 0..1,
    means over the images."""
    from codesign.models.quality import psnr, ssim
    from codesign.train.evaluation import affine_match

    x, y = checks.check_images("quality", restored, scene)
    if x.shape != y.shape or x.dim() not in (2, 4) or min(x.shape[-2:]) < 11:
        raise ConfigError("quality", (tuple(x.shape), tuple(y.shape)), "restored and scene must have one shape, "
                          "(H, W) or (N, 1, H, W), at least 11 px a side")
    x, y = (t[None, None] if t.dim() == 2 else t for t in (x, y))
    m = affine_match(x, y)
    return {"psnr": float(psnr(x.clamp(0, 1), y).mean()), "ssim": float(ssim(x.clamp(0, 1), y).mean()),
            "psnr_matched": float(psnr(m, y).mean()), "ssim_matched": float(ssim(m, y).mean())}


def mask_search(*overrides: str, run_dir: str | Path | None = None) -> dict[str, Any]:
    """A mask-only search (``+experiment=mask_search``, e.g. ``"mask=spline"``, ``"search.max_evals=50"``,
    ``"debug=smoke"``). Returns its figures, metrics.json (``lsr``: the certified peak LSR, ``mtf_mean`` of the
    best design, ``lsr_published`` of the published mask, ...), with ``mask``: the best design as a frozen Mask on
    the search's pupil grid (``psf_and_lsr(mask, cfg=...)``, ``build_camera(mask=mask)``, ``restore_image(...,
    mask=mask)`` take it) and ``run_dir``, where best_mask.json (a record ``mask.init=PATH`` takes), evaluations.csv
    and the figures are written."""
    from codesign.optics.masks import FAMILIES, load_record

    checks.check_overrides("mask_search", overrides, run=True, experiment=True)
    result = run("mask_search", *overrides, run_dir=run_dir)
    record = result["run_dir"] / "best_mask.json"
    kind = load_record(record, "mask.init", "a mask record")["kind"]
    system = optical_system(compose(*overrides, experiment="mask_search"))
    mask = _build_mask({**FAMILIES[kind].Spec.defaults(), "kind": kind, "init": str(record)}, system.grid,
                      system.spec.aperture_diameter_m)
    return {**result, "mask": mask.freeze()}


def train_restorer(*overrides: str, run_dir: str | Path | None = None, experiment: str = "baseline"
                   ) -> dict[str, Any]:
    """Train and evaluate a restoration network on a fixed mask (``+experiment=baseline``; ``experiment="joint"``
    runs the main job, which designs and co-designs the mask too). overrides e.g. ``"model=sgan_b"``,
    ``"trainer.steps=200"``, ``"debug=smoke"``. Writes checkpoint.pt (restore() takes it), evaluation.csv; returns
    metrics.json with ``run_dir``: baseline's ``psnr_<method>_<preset>`` (dB) and ``ssim_<method>_<preset>`` for
    method sgan / sensor / wiener / g1_wiener and preset laser_<alpha_l> / H1 (e.g. ``psnr_sgan_laser_1e6``),
    ``steps``, ``seconds`` (wall, s); the main job's ``masks``, ``systems`` (per system and laser_<alpha_l>:
    ``psnr_matched``, ``psnr``, ``ssim``), ``gains``, ``goal`` and ``checkpoint`` (the co-designed network's);
    with ``"codesign.protocol=single"`` one joint run's ``psnr``, ``psnr_published``, ``lsr``, ``lsr_published``,
    ... (README, docs/codesign.md)."""
    checks.check_experiment("train_restorer experiment", experiment, checks.TRAINING)
    checks.check_overrides("train_restorer", overrides, run=True, experiment=True)
    return run(experiment, *overrides, run_dir=run_dir)
