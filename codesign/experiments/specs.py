"""What an experiment reads from the composed config for the library (issue 58): the configuration is read at the
boundary, here and in each experiment; the library packages take the specs and objects built from it."""
from __future__ import annotations

import logging

from omegaconf import DictConfig, OmegaConf

from codesign.config.runtime import resolve_dtype, to_container
from codesign.design.check import camera_sampling_report
from codesign.design.measured_merit import measured_psf_report
from codesign.design.merit import MetricsSpec
from codesign.errors import ConfigError
from codesign.fab.surface import ExportSpec
from codesign.optics.masks import config_of_design, levels_of_design
from codesign.optics.materials import Material
from codesign.optics.measured import MEASURED_DEFAULTS
from codesign.optics.metrics import require_band_frequencies
from codesign.optics.spec import OpticsSpec

export_log = logging.getLogger("codesign.export")
evaluate_log = logging.getLogger("codesign.evaluate")


def metrics_spec(cfg) -> MetricsSpec:
    """The validated ``metrics`` block of a composed config (defaults when it has none)."""
    return MetricsSpec.from_config(dict(cfg.get("metrics") or {}))


def material_of(cfg) -> Material:
    """The run's Material (``cfg.material``; a configuration without that block, e.g. a checkpoint's from before
    it existed, has the default: fused silica)."""
    return Material.from_config(to_container(cfg.get("material")))


def with_measured_psf(target: DictConfig, cfg: DictConfig, typed: frozenset[str] = frozenset()) -> DictConfig:
    """``target`` (a checkpoint's configuration) with this run's measured-PSF keys (``optics.psf_*`` of ``cfg``)
    when this run gives a PSF file or types one of them (``optics.psf_file=null`` restores the computed PSF of a
    checkpoint fine-tuned on a measured one); else ``target`` as it is: its own measured PSF, if any."""
    optics = cfg.get("optics")
    if optics is None:
        return target
    typed_here = "optics" in typed or any(f"optics.{k}" in typed for k in MEASURED_DEFAULTS)
    if optics.get("psf_file") is None and not typed_here:
        return target
    out = OmegaConf.create(OmegaConf.to_container(target, resolve=True))
    for key, default in MEASURED_DEFAULTS.items():
        out.optics[key] = optics.get(key, default)
    return out


def camera_reports(camera, cfg, log) -> dict:
    """metrics.json's sampling check of a camera's mask and its measured PSF's figures (if any), both over the MTF
    band of ``cfg.metrics``."""
    band = metrics_spec(cfg).mtf_band
    return {**camera_sampling_report(camera, band, log), **measured_psf_report(camera, band, log)}


def plate_settings(cfg: DictConfig) -> tuple:
    """Export's and tolerance's settings, every one validated before any work: (optics, export, material, the
    design's mask settings, dtype)."""
    spec = OpticsSpec.from_config(to_container(cfg.optics))
    ex = ExportSpec.from_config(to_container(cfg.get("export")))
    material = material_of(cfg)
    material.index(spec.wavelength_m)
    ex.plate_n(spec)
    if ex.levels is not None and spec.wrap_waves is None:
        raise ConfigError("export.levels", ex.levels, "a continuous surface (optics.wrap_waves = null) has no etch "
                          "levels: set export.levels=null, or wrap the surface (optics.wrap_waves=1, or m for an "
                          "m-wave multi-order plate)")
    require_band_frequencies(spec, metrics_spec(cfg).mtf_band)  # both report mtf_means of the window
    mask_cfg = config_of_design(to_container(cfg.mask))
    design = levels_of_design(mask_cfg)
    # an 8-level design is built as 8 levels (a continuous surface has none: its phase steps are kept as they are)
    if ex.levels is None and design is not None and design <= 256 and spec.wrap_waves is not None:
        export_log.info("export.levels = null: the design has %d levels, so has the plate (export.levels chooses "
                        "others)", design)
        ex = ex.replace(levels=design)
    dtype = resolve_dtype("precision", cfg.get("precision"))
    return spec, ex, material, mask_cfg, dtype


def eval_settings(cfg) -> dict:
    """Validate ``evaluate.*`` (and load LPIPS / DISTS when given), before any training or simulation: the settings
    codesign.train.evaluation.run_evaluation takes."""
    # here, not at the top: the experiments that evaluate no network (psf, export, ...) never load the networks
    from codesign.models import quality
    from codesign.train.evaluation import EvaluateSpec

    ev = EvaluateSpec.from_config(dict(cfg.get("evaluate") or {}))
    warn_heldout_over_folder(cfg, ev.scenes)
    return {"scenes": ev.scenes, "split": ev.split, "max_scenes": ev.max_scenes, "lasers": list(ev.laser_strengths),
            "stages": list(ev.stages), "tuning": ev.tuning_size, "batch_size": ev.batch_size,
            "perceptual": quality.perceptual_metrics(ev.lpips_weights, ev.dists_weights),
            "overrides": {} if ev.laser_angle_rad is None else {"laser_angle_rad": list(ev.laser_angle_rad)}}


def warn_heldout_over_folder(cfg, scenes: str) -> None:
    """A warning line when the scores will be the shipped photographs' (evaluate.scenes=heldout, the default) while
    the run names a folder of scenes (data.scenes=folder): they used to be reported without a word about the folder.
    Warned, not refused: scoring the fixed held-out set while the folder trains (or tunes the baselines) is a
    legitimate choice, and the one that keeps scores comparable across runs."""
    data = cfg.get("data") or {}
    if scenes == "heldout" and data.get("scenes") == "folder":
        evaluate_log.warning("evaluate.scenes = heldout: the scores are on the photographs shipped for evaluation "
                             "(codesign/data/heldout/), not on data.folder = %s (data.scenes = folder); give "
                             "evaluate.scenes=data to score that folder's evaluate.split", data.get("folder"))
