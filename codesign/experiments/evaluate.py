"""``+experiment=evaluate checkpoint=PATH``: score a trained restorer against the sensor image and classical Wiener
on held-out scenes, per laser strength and robustness stage."""
from __future__ import annotations

import logging
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from codesign.config.runtime import check_seed, explicit_keys, mask_typed, tensorboard_enabled, with_typed_mask
from codesign.errors import ConfigError
from codesign.io import files as io
from codesign.io.tensorboard import log_summary, open_writer
from codesign.train.data import build_simulated_data
from codesign.train.evaluation import run_evaluation
from codesign.train.checkpoint import nonfinite_summary, stored_config_error
from codesign.train.resume import apply_checkpoint_mask, load_trained
from codesign.train.model_setup import run_metrics
from codesign.experiments.specs import camera_reports, eval_settings, with_measured_psf
from codesign.experiments.protocol import Experiment
from codesign.experiments.typed_values import log_typed_values

log = logging.getLogger("codesign.evaluate")


EXPERIMENT = Experiment(
    summary="evaluate a trained checkpoint against the sensor image and classical Wiener",
    first_work="run_evaluation",
    root_keys=("checkpoint",),
    outputs=("metrics.json", "evaluation.csv"),
    measured_psf=True,
)


def merged_eval_config(cfg: DictConfig, ckpt_cfg: DictConfig, typed: frozenset[str],
                       any_size: bool = False) -> DictConfig:
    """The checkpoint's physics, model and data split, with the scene-source keys typed on this command line
    (``typed``: e.g. data.scenes, data.folder; with ``any_size``, a network that takes any size, also
    data.image_size and data.padded_size: it is evaluated at the pixel scale typed), this run's measured PSF
    (optics.psf_*, when it gives one) and its ``evaluate`` block, and the mask when one is typed here (mask=... /
    mask.*=...: a restorer trained for many masks, data.masks, restores through any). Untyped data keys keep the
    checkpoint's values, so the test split is the one held out during training."""
    merged = with_measured_psf(OmegaConf.create(OmegaConf.to_container(ckpt_cfg, resolve=True)), cfg, typed)
    merged = with_typed_mask(merged, cfg, typed)
    for key in data_keys_of_this_run(typed, any_size):
        merged.data[key] = cfg.data.get(key)
    merged.evaluate = cfg.get("evaluate")
    return merged


def data_keys_of_this_run(typed: frozenset[str], any_size: bool = False) -> list[str]:
    """The data keys evaluate takes from this command line (the scene source, the split; the image sizes for a
    network that takes any size), not the checkpoint."""
    source_typed = bool({"data", "data.scenes", "data.folder"} & typed)  # scenes and folder go together
    keys = ("scenes", "folder", "test_fraction", "split_seed", "cache_mb") + (
        ("image_size", "padded_size") if any_size else ())
    return [key for key in keys
            if f"data.{key}" in typed or "data" in typed or (key in ("scenes", "folder") and source_typed)]


def from_this_run(err: ConfigError, cfg: DictConfig, typed: frozenset[str], any_size: bool = False) -> bool:
    """Whether the key ``err`` names holds this run's value in the merged configuration (typed data keys, the
    evaluate block, a measured PSF given here); any other key holds the checkpoint's stored value."""
    key = str(err.key)
    psf_here = cfg.get("optics") is not None and (cfg.optics.get("psf_file") is not None or "optics" in typed or any(
        k.startswith("optics.psf_") for k in typed))
    return (key.startswith("evaluate.") or (key.startswith("optics.psf_") and psf_here)
            or (key.startswith("mask") and mask_typed(typed))
            or any(key == f"data.{k}" for k in data_keys_of_this_run(typed, any_size)))


def simulated_data(merged: DictConfig, cfg: DictConfig, typed: frozenset[str], path, device, seed: int,
                   any_size: bool = False):
    """The simulator of the merged configuration; a value it refuses that came from the checkpoint is named as
    stored in that file (it used to read as if typed here: "data.padded_size = 64: must be >= data.image_size")."""
    try:
        return build_simulated_data(merged, device, seed)
    except ConfigError as err:
        if from_this_run(err, cfg, typed, any_size):
            raise
        raise stored_config_error("checkpoint", path, err) from None


class CheckedRestorer:
    """``model`` whose every restoration is checked: a non-finite output (finite weights that overflow) stops the
    evaluation with a ConfigError naming the checkpoint, instead of tables and figures of "nan dB"."""

    def __init__(self, model, path):
        self._model, self._path = model, path

    def __getattr__(self, name):
        return getattr(self._model, name)

    def restore(self, *args, **kwargs) -> dict:
        """The model's restoration, refused (ConfigError naming the checkpoint) when any output holds a non-finite
        value."""
        out = self._model.restore(*args, **kwargs)
        for name, value in out.items():
            bad = nonfinite_summary(value) if torch.is_tensor(value) else None
            if bad:
                raise ConfigError("checkpoint", str(self._path), f"its network's output {name!r} on the evaluation's "
                                  f"simulated captures holds {bad}: its weights are finite but the network does not "
                                  f"compute finite images (evaluation stopped, no metrics.json)")
        return out


def refuse_other_model(cfg: DictConfig, ckpt_cfg: DictConfig, typed: frozenset[str], facts: dict, path) -> None:
    """evaluate runs the checkpoint's own model: a model= / model.* typed on the command line that describes
    another one is refused (it used to be recorded in the run's config while the checkpoint's model ran)."""
    if not any(k == "model" or k.startswith("model.") for k in typed):
        return
    asked = OmegaConf.to_container(cfg.model, resolve=True) if cfg.get("model") is not None else None
    if asked != OmegaConf.to_container(ckpt_cfg.model, resolve=True):
        raise ConfigError("model", asked, f"evaluate runs the model of checkpoint {path} (model.kind="
                          f"{facts.get('kind', ckpt_cfg.model.get('kind'))}, variant={facts.get('variant')}, size="
                          f"{facts.get('size')}): leave model and model.* off the command line")


def run(cfg: DictConfig, run_dir: Path, device: torch.device) -> float:
    """A trained checkpoint (checkpoint=PATH, or pretrained) evaluated on held-out scenes simulated through its own
    physics (its learned mask, unless a mask is typed here), against the sensor image and classical Wiener; writes
    metrics.json, the evaluation tables and panels; returns the restorer's PSNR at alpha_l = 1e6. Steps: load
    (the checkpoint and the merged configuration), build (the simulated data), evaluate, report."""
    path = cfg.get("checkpoint")
    if not path:
        raise ConfigError("checkpoint", path, "give the trained model: +experiment=evaluate checkpoint=PATH")
    ev = eval_settings(cfg)
    model, generators, ckpt_cfg, state = load_trained(path, device)
    typed = explicit_keys()
    refuse_other_model(cfg, ckpt_cfg, typed, {"kind": model.kind, **model.summary()}, path)
    merged = merged_eval_config(cfg, ckpt_cfg, typed, model.any_size)
    log_typed_values(log, "evaluate", cfg, merged, typed)
    seed = check_seed(cfg)
    data = simulated_data(merged, cfg, typed, path, device, seed, model.any_size)
    if not mask_typed(typed):  # a co-designed checkpoint's learned mask, unless a mask is given here
        apply_checkpoint_mask(data.camera.mask, state, path)
        data.camera.invalidate()
    metrics = {**run_metrics(model, device, data), "checkpoint": str(path), "steps": int(state["step"]),
               **camera_reports(data.camera, merged, log)}
    metrics.update(run_evaluation(ev, CheckedRestorer(model, path), generators, data, run_dir, seed))
    io.write_json(run_dir / "metrics.json", metrics)
    log_summary(open_writer(run_dir, tensorboard_enabled(cfg)), {**model.summary(), "checkpoint": str(path)},
                metrics)
    return metrics.get(f"psnr_{model.method}_laser_1e6", float("nan"))
