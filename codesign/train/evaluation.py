"""Evaluation of a restoration model against honest baselines, per laser strength and per robustness stage.

Methods (all scored on the sensor's field of view, the central image_size x image_size, clamped to [0, 1]):
  sensor      the raw sensor image, black level removed, with a global gain/offset fitted on a tuning set
  wiener      classical Wiener deconvolution with the true PSF: black level removed, edge-replicated padding,
              noise-to-signal ratio tuned on the tuning set (log grid, best affine-matched PSNR), then the
              fitted gain/offset
  g1_wiener   the same classical Wiener filter applied to the network's pre-restored irradiance I_b^ (the SGAN's
              G1 output; only for restorers that have one), tuned separately
  sgan        the restorer (its ``method`` name: sgan for the sandwich GAN), no calibration
The tuning set is drawn from the training distribution (train split, fixed seed), never from the test scenes.
Metrics: 1-MSE, PSNR, SSIM, MS-SSIM, and 1-LPIPS / DISTS when their weights are given by path, all against the
scene b as the paper scores them; plus psnr_matched / ssim_matched after a per-image least-squares gain and offset
(the background strength alpha_b scales the whole image and is not known to any method, so raw PSNR mixes a
brightness guess with restoration; the affine-matched scores isolate the restoration of structure).
"""
from __future__ import annotations

import csv
import io as _io
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import torch

from codesign.camera import field_of_view as centre
from codesign.config.store import register, spec_node
from codesign.data.scenes import heldout_source
from codesign.data.params import (
    LASER_STRENGTHS,
    PRESETS,
    ROBUSTNESS_STAGES,
    alpha_tag,
    laser_preset_name,
)
from codesign.errors import (
    ConfigError,
    refuse_repeats,
    require_choice,
    require_list,
    require_number,
    require_numbers,
)
from codesign.io import files as io
from codesign.models import quality
from codesign.models.fill import replicate_pad
from codesign.models.wiener import classical_wiener, classical_wiener_sweep
from codesign.spec_base import SpecMixin

log = logging.getLogger("codesign.evaluate")

BASELINES = ("sensor", "wiener", "g1_wiener")
NSR_GRID = tuple(10.0 ** e for e in np.arange(-6.0, 2.01, 0.25))


def remove_black_level(batch: dict, full_well_e: float) -> torch.Tensor:
    """The normalized sensor image minus its read-noise offset mu_r / e_sat (DN / (G e_sat) = e / e_sat), on the
    sensor's field only (the zero padding stays zero): the calibration any classical pipeline starts with."""
    s = batch["sensor"]
    offset = batch["read_noise_mean_e"].to(s.device, s.dtype).view(-1, 1, 1, 1) / full_well_e
    return s - offset * (s != 0)


def fit_affine(x: torch.Tensor, y: torch.Tensor) -> tuple[float, float]:
    """Least-squares gain and offset with y ~ a x + c over all pixels (closed form, float64; a constant x gives
    a = 0, c = mean y)."""
    xf, yf = x.double().flatten(), y.double().flatten()
    xm, ym = xf.mean(), yf.mean()
    var = (xf - xm).square().mean()
    a = float(((xf - xm) * (yf - ym)).mean() / var) if float(var) > 0 else 0.0
    return a, float(ym - a * xm)


def affine_match(x: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per image, a x + c with (a, c) the least-squares fit to the target: removes the global brightness and
    contrast, which the sensor cannot identify (alpha_b is unknown), so that what remains measures structure."""
    xm, tm = x.mean(dim=(-2, -1), keepdim=True), target.mean(dim=(-2, -1), keepdim=True)
    cov = ((x - xm) * (target - tm)).mean(dim=(-2, -1), keepdim=True)
    var = (x - xm).square().mean(dim=(-2, -1), keepdim=True)
    a = torch.where(var > 0, cov / var.clamp_min(1e-30), torch.zeros_like(var))
    return (a * (x - xm) + tm).clamp(0, 1)


def tune_nsr(outputs: Iterable[torch.Tensor], target: torch.Tensor, size: int,
             grid: Sequence[float] = NSR_GRID) -> float:
    """The noise-to-signal ratio of ``grid`` (default NSR_GRID) whose Wiener output restores ``target`` best: the one
    Wiener nsr tuning of the evaluation's baselines, of a restorer's Wiener base (codesign/train/base_tuning.py) and
    of the design benchmark's Wiener references (a noise gain on a spectral nsr there).

    ``outputs``: one restoration per value of ``grid``, in its order, (B, 1, H, W) each (an iterable: each may be
    computed when asked); ``target``: the scenes' central ``size`` x ``size`` pixels, (B, 1, size, size). Tuned for
    structure (per-image gain/offset matched): a global gain fitted across images of unknown alpha_b shrinks every
    candidate towards the mean and would make the choice arbitrary. The criterion is the images' pooled squared
    error, not their mean PSNR: a flat crop (sky, a black border) is matched almost exactly by every candidate, and
    its near-unbounded PSNR would weigh most.
    """
    errors = [float((affine_match(centre(x, size), target) - target).square().mean()) for x in outputs]
    return grid[int(np.argmin(errors))]


class Evaluator:
    """Tune the baselines once, then score every method on any simulated batch.

    ``model``: a Restorer; ``generators``: the modules it restores with (its own or EMA copies); ``data``: a
    SimulatedData (batches, the camera's OTF and sensor)."""

    def __init__(self, model, generators, data, perceptual: dict | None = None, *, batch_size: int):
        self.model, self.generators, self.data = model, generators, data
        self.n = data.image_size
        self.perceptual = perceptual if perceptual is not None else quality.perceptual_metrics(None, None)
        self.batch_size = batch_size
        self.calib: dict[str, dict] = {}
        self.has_i_b: bool | None = None  # known after the first restoration: g1_wiener needs the network's I_b
        self._tuning: tuple[torch.Tensor, int] | None = None  # per-condition tuning: (scenes, noise seed)
        self.calib_by_condition: dict[str, dict] = {}

    def tune_per_condition(self, scenes: torch.Tensor, seed: int) -> None:
        """Tune the baselines for every scored condition on its own: ``scenes`` (training-split crops, never the
        scored ones) simulated under that condition with noise ``seed``. One tuning batch drawn from the training
        distribution (lasers of every strength, every exposure) leaves Wiener's output uncorrelated with the
        scene for most images, so every nsr scores alike and the choice is noise (nsr 100 on a CPU, 1e-6 on a GPU
        for the same batch): a classical pipeline is tuned for the conditions it is judged on."""
        self._tuning, self.calib_by_condition = (scenes, seed), {}

    def _calibrate_for(self, preset: str, overrides: dict | None) -> None:
        if self._tuning is None:
            return
        key = preset + ("" if not overrides else f" {sorted(overrides.items())}")
        if key not in self.calib_by_condition:
            scenes, seed = self._tuning
            self.calib_by_condition[key] = self.tune(self.data.preset_batch(scenes, preset, seed=seed,
                                                                            **(overrides or {})))
        self.calib = self.calib_by_condition[key]

    @property
    def methods(self) -> tuple[str, ...]:
        """The evaluated methods in table order: the baselines this restorer allows, then the restorer."""
        return tuple(b for b in BASELINES if b != "g1_wiener" or self.has_i_b) + (self.model.method,)

    # ---- raw outputs of each method (before calibration) ----------------------------------------------------
    @torch.no_grad()
    def _network(self, batch: dict) -> dict:
        """Black-level-corrected sensor image and the network's outputs, in chunks of ``batch_size``."""
        s = remove_black_level(batch, self.data.camera.sensor.full_well_e)
        outs = [self.model.restore(chunk, self.data.otf, self.generators)
                for chunk in batch["sensor"].split(self.batch_size)]
        self.has_i_b = all("i_b" in o for o in outs)
        net = {"s": s, "b": torch.cat([o["restored"] for o in outs])}
        if self.has_i_b:
            net["i_b"] = torch.cat([o["i_b"] for o in outs])
        return net

    def _outputs(self, net: dict, nsr: dict) -> dict:
        otf = self.data.otf
        out = {"sensor": centre(net["s"], self.n), self.model.method: centre(net["b"], self.n),
               "wiener": centre(classical_wiener(replicate_pad(net["s"], self.n), otf, nsr["wiener"]), self.n)}
        if "i_b" in net:
            out["g1_wiener"] = centre(classical_wiener(net["i_b"], otf, nsr["g1_wiener"]), self.n)
        return out

    @torch.no_grad()
    def tune(self, batch: dict) -> dict:
        """Choose each Wiener's nsr (best affine-matched PSNR) and each baseline's global gain/offset."""
        target = centre(batch["scene"], self.n)
        net = self._network(batch)
        inputs = {"wiener": replicate_pad(net["s"], self.n)}
        if "i_b" in net:
            inputs["g1_wiener"] = net["i_b"]
        best_nsr = {name: tune_nsr(classical_wiener_sweep(y, self.data.otf, NSR_GRID), target, self.n)
                    for name, y in inputs.items()}
        tuned = self._outputs(net, best_nsr)
        self.calib = {"nsr": best_nsr}
        for name in self.methods[:-1]:
            self.calib[name] = fit_affine(tuned[name], target)
        log.info("baselines tuned on %d images: nsr %s", target.shape[0],
                 ", ".join(f"{k} {v:.3g}" for k, v in best_nsr.items()))
        return self.calib

    # ---- scoring --------------------------------------------------------------------------------------------
    @torch.no_grad()
    def restore_all(self, batch: dict) -> dict:
        """Every method's restoration of ``batch``, with the tuned nsr and gain/offset, clamped to [0, 1]: name ->
        (B, 1, n, n)."""
        raw = self._outputs(self._network(batch), self.calib["nsr"])
        out = {}
        for name in self.methods:
            x = raw[name]
            if name in self.calib:
                a, c = self.calib[name]
                x = a * x + c
            out[name] = x.clamp(0, 1)
        return out

    @torch.no_grad()
    def score(self, images: dict, target: torch.Tensor, per_scene: dict | None = None) -> dict:
        """Every metric of every method, the mean over the images; ``per_scene``: a dict that receives each
        method's PSNR after the gain/offset match image by image (paired comparisons of two systems)."""
        table = {}
        for name, x in images.items():
            row = {"one_minus_mse": quality.one_minus_mse(x, target), "psnr": quality.psnr(x, target),
                   "ssim": quality.ssim(x, target), "ms_ssim": quality.ms_ssim(x, target)}
            for pname, fn in self.perceptual.items():
                if callable(fn):
                    row[pname] = fn(x, target)
            matched = affine_match(x, target)
            row["psnr_matched"] = quality.psnr(matched, target)
            row["ssim_matched"] = quality.ssim(matched, target)
            if per_scene is not None:
                per_scene[name] = row["psnr_matched"].flatten().tolist()
            table[name] = {k: float(v.mean()) for k, v in row.items()}
        return table

    @torch.no_grad()
    def score_preset(self, scenes: torch.Tensor, preset: str, seed: int, overrides: dict | None = None,
                     per_scene: dict | None = None) -> tuple[dict, dict, torch.Tensor, dict]:
        """(batch, restored images, target, table): ``scenes`` simulated under ``preset`` with noise ``seed``, every
        method restored and scored against the centre of the scene (``per_scene``: as ``score``); the baselines
        tuned for ``preset`` first when tune_per_condition was called."""
        self._calibrate_for(preset, overrides)
        batch = self.data.preset_batch(scenes, preset, seed=seed, **(overrides or {}))
        images = self.restore_all(batch)
        target = centre(batch["scene"], self.n).clamp(0, 1)
        return batch, images, target, self.score(images, target, per_scene)


def conditions(laser_strengths=LASER_STRENGTHS, stages=tuple(ROBUSTNESS_STAGES)) -> list[str]:
    """Preset names: laser_0, laser_1e1 .. laser_1e6 (figure settings) then the robustness stages."""
    return [laser_preset_name(float(a)) for a in laser_strengths] + list(stages)


def evaluate(evaluator: Evaluator, scenes: torch.Tensor, names: list[str], presets: list[str], seed: int,
             run_dir: Path, overrides: dict | None = None, keep: tuple[str, ...] = ()) -> tuple[dict, dict, dict]:
    """Score every method under every preset; write evaluation.csv and the panels. Returns the tables (metrics.json
    entries), each preset's per-scene PSNR after the gain/offset match, and the images of the presets in ``keep``
    (input, every method, truth; for figures that compare runs)."""
    results, rows, per_scene, kept = {}, [], {}, {}
    for j, preset in enumerate(presets):
        per_scene[preset] = {}
        batch, images, target, table = evaluator.score_preset(scenes, preset, seed + 1000 + j, overrides,
                                                              per_scene[preset])
        results[preset] = table
        for method, metrics in table.items():
            rows.append({"condition": preset, "method": method, **metrics})
        shown = {"input": centre(batch["sensor"], evaluator.n), **images}
        if preset in keep:
            kept[preset] = {**{k: v.detach().cpu() for k, v in shown.items()}, "truth": target.cpu()}
        # the restorer's column titled with its configured name
        network = (evaluator.model.method, getattr(evaluator.model.spec, "name", None))
        io.save_figure(run_dir / f"panel_{preset}.png", panel_figure(shown, target, names, preset, table, network))
        log.info("%-10s %s", preset, "  ".join(f"{m} {table[m]['psnr']:.2f} dB/{table[m]['ssim']:.3f} "
                                             f"(matched {table[m]['psnr_matched']:.2f})" for m in table))
    write_csv(run_dir / "evaluation.csv", rows)
    return results, per_scene, kept


def write_csv(path: Path, rows: list[dict]) -> None:
    """Rows (dicts with the same keys) as CSV, floats at 6 significant digits, atomically."""
    keys = list(rows[0]) if rows else []
    buf = _io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    io.atomic_write_bytes(path, lambda f: f.write(buf.getvalue().encode()))


# readable column titles of the evaluation figures (code name -> what the column shows)
METHOD_TITLES = {"input": "sensor image\n(autoscaled)", "sensor": "sensor image\n(gain/offset matched)",
                 "wiener": "classical Wiener", "g1_wiener": "Wiener after G1\n(laser removed)",
                 "sgan": "SGAN network", "wiener_unet": "Wiener + U-Net\nnetwork", "truth": "ground truth"}


def method_title(name: str, network: str | None = None) -> str:
    """A column's title; ``network``: the restorer's name as configured (model.name), given for its column."""
    title = METHOD_TITLES.get(name, name)
    return f"{network}\n({title})" if network else title


def preset_description(preset: str) -> str:
    """What an evaluation preset is: "robustness stage H1: laser strength alpha_l = 1e6, ..." or "laser_1e6:
    laser strength alpha_l = 1e6 (the paper's figure settings)"."""
    from codesign.data.params import PRESETS, ROBUSTNESS_STAGES

    values = PRESETS.get(preset)
    if values is None:
        return preset
    if preset in ROBUSTNESS_STAGES:
        return (f"robustness stage {preset}: laser strength alpha_l = {alpha_tag(values['alpha_l'])}, "
                f"background alpha_b = "
                f"{values['alpha_b']:g}, photon noise c1 = {values['c1']:g}")
    if preset.startswith("laser_"):
        return f"{preset}: laser strength alpha_l = {alpha_tag(values['alpha_l'])} (the paper's figure settings)"
    return preset


def panel_figure(images: dict, target: torch.Tensor, names: list[str], preset: str, table: dict,
                 network: tuple[str, str | None] | None = None):
    """The first three scenes (rows) under ``preset``: the sensor image, each method and the truth (columns), each
    method's title with its PSNR, the mean over every evaluated scene; ``network``: (the restorer's column, its
    configured name), the name shown in that column's title."""
    column, name = network or (None, None)
    cols = list(images) + ["truth"]
    rows = min(len(names), 3)
    from codesign.io.plots import plt  # matplotlib only when a figure is drawn (import codesign stays light)

    fig, axes = plt.subplots(rows, len(cols), figsize=(2.1 * len(cols), 2.2 * rows + 0.6), squeeze=False)
    for i in range(rows):
        for j, col in enumerate(cols):
            ax = axes[i][j]
            img = (target if col == "truth" else images[col])[i, 0].detach().cpu().numpy()
            vmax = max(float(np.percentile(img, 99.5)), 1e-6) if col == "input" else 1.0
            ax.imshow(img, cmap="gray", vmin=0, vmax=vmax)
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                title = method_title(col, name if col == column else None)
                if col in table:
                    title += f"\n{table[col]['psnr']:.2f} dB"
                ax.set_title(title, fontsize=8)
            if j == 0:
                ax.set_ylabel(names[i], fontsize=8)
    n = target.shape[0]
    shown = f" (rows: the first {rows})" if rows < n else ""
    fig.suptitle(f"{preset_description(preset)}\nPSNR [dB]: the mean over the {n} evaluated scene{'s' * (n != 1)}"
                 f"{shown}", fontsize=9)
    fig.tight_layout()
    return fig


def flat_summary(results: dict) -> dict:
    """metrics.json keys like psnr_sgan_laser_1e6 for quick reading and TensorBoard hparams."""
    out = {}
    for cond, table in results.items():
        for method, metrics in table.items():
            for k, v in metrics.items():
                out[f"{k}_{method}_{cond}"] = v
    return out


EVAL_SCENES = ("heldout", "data")


@dataclass(frozen=True)
class EvaluateSpec(SpecMixin):
    """The ``evaluate`` block. scenes: heldout (the 16 photographs shipped for evaluation only,
    codesign/data/heldout/, never trained on) | data (the data source's ``split``: data.scenes / data.folder);
    split: test | train | all (with scenes=data); max_scenes: the first this many scenes; laser_strengths: the
    paper's figure strengths evaluated (laser on axis); stages: robustness stages (supplement table); tuning_size:
    training-split crops that, simulated under each condition, tune the baselines' nsr and gain for it;
    batch_size: images per network pass (memory); laser_angle_rad: [n_u, n_v] to move the laser off axis in every
    condition, null = the presets (on axis); lpips_weights, dists_weights: paths of LPIPS (VGG16) / DISTS weights,
    null = reported as unavailable."""

    scenes: str = "heldout"
    split: str = "test"
    max_scenes: int = 16
    laser_strengths: tuple = LASER_STRENGTHS
    stages: tuple = tuple(ROBUSTNESS_STAGES)
    tuning_size: int = 8
    batch_size: int = 8
    laser_angle_rad: tuple | None = None
    lpips_weights: str | None = None
    dists_weights: str | None = None
    prefix: str = field(default="evaluate", compare=False, repr=False)

    def __post_init__(self) -> None:
        put = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731
        require_choice("evaluate.scenes", self.scenes, EVAL_SCENES)
        require_choice("evaluate.split", self.split, ("test", "train", "all"))
        put("max_scenes", require_number("evaluate.max_scenes", self.max_scenes, lo=1, hi=100000, integer=True))
        allowed = ", ".join(alpha_tag(a) for a in LASER_STRENGTHS)
        lasers = require_list("evaluate.laser_strengths", self.laser_strengths,
                              f"must be a list of the paper's strengths {allowed}")
        for i, a in enumerate(lasers):
            a = require_number(f"evaluate.laser_strengths[{i}]", a, lo=0)
            if laser_preset_name(float(a)) not in PRESETS or PRESETS[laser_preset_name(float(a))]["alpha_l"] != a:
                raise ConfigError(f"evaluate.laser_strengths[{i}]", a,
                                  f"must be one of the paper's strengths {allowed}")
        put("laser_strengths", tuple(float(a) for a in lasers))
        refuse_repeats("evaluate.laser_strengths", self.laser_strengths)  # each would be evaluated again
        stages = require_list("evaluate.stages", self.stages,
                              f"must be a list of robustness stages from {', '.join(ROBUSTNESS_STAGES)} (or [])")
        for i, st in enumerate(stages):
            require_choice(f"evaluate.stages[{i}]", st, tuple(ROBUSTNESS_STAGES))
        put("stages", tuple(stages))
        put("tuning_size", require_number("evaluate.tuning_size", self.tuning_size, lo=1, hi=256, integer=True))
        put("batch_size", require_number("evaluate.batch_size", self.batch_size, lo=1, hi=4096, integer=True))
        if self.laser_angle_rad is not None:
            put("laser_angle_rad", tuple(require_numbers("evaluate.laser_angle_rad", self.laser_angle_rad,
                                                         "must be [n_u, n_v] in radians, or null", 2)))


register("evaluate", "default", spec_node(EvaluateSpec))


def run_evaluation(ev: dict, model, generators, data, run_dir: Path, seed: int, keep: tuple[str, ...] = ()) -> dict:
    """Tune the baselines per condition on training-split crops, then score every method on the held-out
    photographs (evaluate.scenes=heldout) or the chosen split of the data source (evaluate.scenes=data).
    ``keep``: presets whose images the result carries under "images" (not JSON: pop it before writing metrics)."""
    source, split = (heldout_source(), "all") if ev["scenes"] == "heldout" else (data.source, ev["split"])
    names = source.split_names(split)[: ev["max_scenes"]]
    if not names:
        raise ConfigError("evaluate.split", ev["split"], "has no scenes in this data source")
    scenes = source.fixed_batch(names, data.camera.scene_size)
    evaluator = Evaluator(model, generators, data, ev["perceptual"], batch_size=ev["batch_size"])
    evaluator.tune_per_condition(data.validation_scenes(ev["tuning"]), data.validation_noise_seed)
    presets = conditions(ev["lasers"], ev["stages"])
    results, per_scene, kept = evaluate(evaluator, scenes, names, presets, seed, run_dir, ev["overrides"], keep)
    calib = evaluator.calib_by_condition
    perceptual = {k: ("available" if callable(v) else v) for k, v in ev["perceptual"].items()}
    out = {"evaluation": results, "evaluation_scenes": names, "evaluation_per_scene_psnr_matched": per_scene,
           "baseline_calibration": calib, "perceptual_metrics": perceptual, **flat_summary(results)}
    return {**out, "images": kept} if keep else out
