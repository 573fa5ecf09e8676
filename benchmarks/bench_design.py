"""Mask design: every family searched under the published mask's MTF floor, against the physical limit.

For each family (halfring, spiral, zernike, spline, pixel) one ``+experiment=mask_search`` run at the default
optics (384 samples across the aperture, 640-pixel window): the best LSR at the published mask's mtf_mean
(factor 1.0, the family's energy floor), its ratio to the limit, its restorability, the same after 8-level
quantization, and the re-check on a pupil grid twice as fine with a window twice as wide; then the floor sweep
(Pareto front) of each; then the half rings on a 1280 window, and the spline on a 1280 window that holds its whole
PSF (512 samples across the aperture, the floor the published mask's mtf_mean there). Then restorability
validated: over 19 masks of every family spanning the LSR range, the predicted PSNR against the PSNR of tuned
Wiener filters measured on simulated captures of held-out photographs (../shared/data/scenes when present, else
the built-in scenes; Spearman rank correlation). Then the restorability objective: the best design at an LSR
ceiling of the published LSR and of 1e-3, measured the same way. Every search's outputs stay in
results/<scale>/design/<run>/.

    python -m benchmarks --only design [--scale full]
    python -m benchmarks.bench_design --scale full --redo pixel   # those families again, the rest kept
    python -m benchmarks.bench_design --scale full --report       # re-render design.json
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import Report, compose, markdown_table, write_json

FAMILIES = ("halfring", "spiral", "zernike", "spline", "pixel")
# evaluations per start of the main floor, the sweep's factors and its evaluations per (warm) start
BUDGET = {
    "quick": {"max_evals": {"halfring": 60, "spiral": 40, "zernike": 150, "spline": 150, "pixel": 150},
              "factors": [], "sweep_evals": 0, "starts": {"halfring": 2, "spiral": 2},
              "objective_evals": 100},
    "full": {"max_evals": {"halfring": 150, "spiral": 150, "zernike": 2400, "spline": 2400, "pixel": 2400},
             "factors": [0.7, 0.85, 1.15], "sweep_evals": 1200, "starts": {"halfring": 4, "spiral": 4},
             "objective_evals": 1600},
}
QUANTIZED = "8"
WHOLE = "spline, 1280 window, 512 across"


def _cfg(overrides: list[str]):
    return compose(["+experiment=mask_search", "logging.tensorboard=false", *overrides])


def _search(run_dir: Path, overrides: list[str]) -> dict:
    """One mask_search run (in this process); its metrics.json content, with the wall time."""
    from codesign.experiments.mask_search import run

    cfg = _cfg(overrides)
    torch.manual_seed(0)
    t0 = time.perf_counter()
    run(cfg, run_dir, torch.device("cpu"))
    return {**json.loads((run_dir / "metrics.json").read_text()), "wall_seconds": time.perf_counter() - t0}


def family_searches(scale: str, out: Path, only: tuple[str, ...] = FAMILIES
                    ) -> tuple[dict[str, dict], dict[str, dict]]:
    """Every family of ``only`` at the default optics (its metrics.json content), and, for all of them, the extra
    runs."""
    b = BUDGET[scale]
    results = {}
    for fam in only:
        over = [f"mask={fam}", f"search.max_evals={b['max_evals'][fam]}",
                "search.pareto_factors=" + ("[" + ",".join(f"{f:g}" for f in b["factors"] + [1.0]) + "]"
                                            if b["factors"] else "null"),
                "search.pareto_starts=1", f"search.pareto_max_evals={max(b['sweep_evals'], 1)}"]
        if fam in b["starts"]:
            over.append(f"search.starts={b['starts'][fam]}")
        print(f"  searching {fam}: {' '.join(over)}", flush=True)
        results[fam] = _search(out / "design" / fam, over)
        _progress(fam, results[fam])
    if tuple(only) != FAMILIES:
        return results, {}
    # no half-ring mask keeps its light in the 640 window (the published one holds 87 %): the family again on a
    # window twice as wide, where its re-check can hold (its MTF floor: the published mask's on that window)
    over = ["mask=halfring", "optics.focal_n=1280", f"search.max_evals={b['max_evals']['halfring']}",
            f"search.starts={b['starts']['halfring']}", "search.pareto_factors=null"]
    print(f"  searching halfring on the 1280 window: {' '.join(over)}", flush=True)
    extra = {"halfring, 1280 window": _search(out / "design" / "halfring_1280", over)}
    _progress("halfring, 1280 window", extra["halfring, 1280 window"])
    # the goal on a window that holds the whole PSF: the spline on the 1280 window, its floor the published mask's
    # mtf_mean there, with 512 samples across the aperture so the window stays well inside the replica period
    # (7.48 um pitch: 9.31 mm against 6.91 mm; at 384 across, 6.98 mm, light beyond the window wraps in)
    over = ["mask=spline", "mask.control_spacing=2.667", "optics.focal_n=1280", "optics.pupil_pitch_m=7.48e-6",
            f"search.max_evals={b['max_evals']['spline']}", "search.pareto_factors=null"]
    print(f"  searching spline on the 1280 window: {' '.join(over)}", flush=True)
    extra[WHOLE] = _search(out / "design" / "spline_whole_window", over)
    _progress(WHOLE, extra[WHOLE])
    return results, extra


def _record(run_dir: Path) -> str:
    """A search's best_mask.json, or the gzip-compressed copy (best_mask.json.gz) that results/full keeps of a large
    one; --redo reads the families it does not search again from there."""
    plain = run_dir / "best_mask.json"
    return str(plain if plain.is_file() else plain.with_name("best_mask.json.gz"))


def _progress(fam: str, m: dict) -> None:
    print(f"  {fam}: LSR {m['lsr']:.4g} ({m['lsr_over_limit']:.2f}x the limit), mtf_mean {m['mtf_mean']:.4g}, "
          f"{m['evaluations']} evaluations in {m['seconds']:.0f} s; re-check "
          f"{'agrees' if m['check'] and m['check']['agree'] else 'FAILS'}", flush=True)


def _family_rows(results: dict) -> list[list]:
    rows = []
    for fam, m in results.items():
        q = m["quantized"][QUANTIZED]
        chk = m["check"] or {}
        rows.append([fam, m["focal_n"], m["parameters"], m["evaluations"], float(m["seconds"]), float(m["lsr"]),
                     float(m["mtf_mean"]), float(m["window_energy"]), float(m["lsr_over_limit"]),
                     float(m["restorability"]), float(q["lsr"]), float(q["restorability"]),
                     f"{100 * chk.get('max_deviation', float('nan')):.1f}% ({'ok' if chk.get('agree') else 'FAILS'})",
                     "yes" if m["feasible"] else "NO"])
    return rows


def fronts_figure(path: Path, results: dict) -> Path:
    """LSR against mtf_mean: every family's front (its sweep), the published mask, the limit curve."""
    from codesign.design.tradeoff_figures import lsr_mtf_figure
    from codesign.design.limits import MTFLimit
    from codesign.io.files import save_figure
    from codesign.optics import OpticalSystem, OpticsSpec

    any_m = next(iter(results.values()))
    system = OpticalSystem(OpticsSpec(), dtype=torch.float64)
    limit = MTFLimit(system, (any_m["mtf_band_low"], any_m["mtf_band_high"]))
    points = {fam: sorted((p["mtf_mean"], p["lsr"]) for p in m["pareto"] if p["feasible"]) or
              [(m["mtf_mean"], m["lsr"])] for fam, m in results.items()}
    refs = {"published mask": (any_m["mtf_mean_published"], any_m["lsr_published"])}
    save_figure(path, lsr_mtf_figure(points, limit, refs, "best LSR per MTF floor, every family",
                                     [any_m["mtf_mean_published"]]))
    return path


# ---- restorability: predicted against measured -----------------------------------------------------------------
# held-out photographs for the measurement (outside the project: the built-in scenes are the fallback)
HELD_OUT = Path(__file__).resolve().parents[2] / "shared" / "data" / "scenes"
GAINS = tuple(10.0 ** e for e in np.arange(-1.0, 4.01, 0.25))


def _validation_masks(results: dict, out: Path):
    """(label, mask config, parameter vector or None) spanning the families and the LSR range: the uncoded
    aperture, the published mask, each family's best design, defocus surfaces and spirals of several strengths,
    random half rings, a random Zernike surface."""
    rng = np.random.default_rng(3)
    masks = [("uncoded", {"kind": "zernike", "init": "zero"}), ("published", {"kind": "halfring"})]
    masks += [(f"best {fam}", {"kind": fam, "init": _record(out / "design" / fam),
                               **({"preset": None} if fam == "halfring" else {})}) for fam in results]
    for a in (8.0, 20.0, 60.0, 120.0):
        masks.append((f"defocus {a:g} rad", {"kind": "spline", "init": "defocus", "defocus_rad": a}))
    for charge, ax in ((1.0, 2.0), (4.0, 8.0), (10.0, 20.0), (2.0, 30.0)):
        masks.append((f"spiral {charge:g}/{ax:g}", {"kind": "spiral", "charge": charge, "axicon_cycles": ax,
                                                     "defocus_rad": 0.0}))
    for i in range(3):
        masks.append((f"half rings random {i}", {"kind": "halfring", "preset": None,
                                                 "r": rng.uniform(1, 60, 5).round(2).tolist(),
                                                 "theta": rng.uniform(0, 6.28, 5).round(2).tolist()}))
    masks = [(label, cfg, None) for label, cfg in masks]
    masks.append(("zernike random", {"kind": "zernike", "init": "zero"}, rng.normal(0.0, 4.0, 36)))
    return masks


def _camera(mask_cfg: dict, vector=None):
    """A frozen camera of the default optics and sensor with this mask."""
    from omegaconf import OmegaConf

    from codesign.camera import build_camera

    cfg = OmegaConf.create(OmegaConf.to_container(_cfg([]), resolve=True))  # unstructured: any family's keys
    cfg.mask = mask_cfg
    camera = build_camera(cfg, torch.device("cpu"))
    if vector is not None:
        camera.mask.set_vector(vector)
        camera.invalidate()
    return camera


class WienerReference:
    """The tuned Wiener filters the prediction is validated against, on simulated captures (figure settings,
    laser off): the classical filter with the model's scene spectrum, nsr(f) = g N / S(f), and the Evaluator's
    constant-nsr filter; each tuned (g over GAINS, resp. nsr over NSR_GRID) on the built-in training scenes by the
    evaluation's one tuning (codesign.train.evaluation.tune_nsr), then scored (affine-matched PSNR over the field)
    on the evaluation scenes."""

    def __init__(self, module, tuning: torch.Tensor, scenes: torch.Tensor):
        self.module, self.tuning, self.scenes = module, tuning, scenes

    def _capture(self, camera, batch, seed):
        from codesign.camera import field_of_view
        from codesign.data.params import fixed_scene_params
        from codesign.train.evaluation import remove_black_level, replicate_pad

        n = camera.image_size
        params = fixed_scene_params(batch.shape[0], alpha_l=0.0)
        out = camera(batch, params, seed=seed)
        out["read_noise_mean_e"] = params.read_noise_mean_e  # the black level, as the training data carries it
        y = replicate_pad(remove_black_level(out, camera.sensor.full_well_e), n).to(torch.float64)
        return y, field_of_view(out["scene"], n).to(torch.float64)

    def _spectral(self, camera, y, gain):
        from codesign.camera import field_of_view
        from codesign.models.wiener import wiener_filter

        p = y.shape[-1]
        fy, fx = torch.fft.fftfreq(p, dtype=torch.float64), torch.fft.rfftfreq(p, dtype=torch.float64)
        power = self.module.spectrum(torch.sqrt(fy[:, None] ** 2 + fx[None, :] ** 2))
        power[0, 0] = 1e2 * power[0, 1]  # the mean passes (compared after a gain / offset match anyway)
        noise = self.module.noise / self.module.alpha_b**2
        return field_of_view(wiener_filter(y, camera.otf, power, noise * gain), camera.image_size)

    def _constant(self, camera, y, nsr):
        from codesign.camera import field_of_view
        from codesign.models.wiener import classical_wiener

        return field_of_view(classical_wiener(y, camera.otf, nsr), camera.image_size)

    @torch.no_grad()
    def __call__(self, camera) -> dict:
        from codesign.models import quality
        from codesign.train.evaluation import NSR_GRID, affine_match, tune_nsr

        def score(x, target):
            return float(quality.psnr(affine_match(x, target), target).mean())

        n = camera.image_size
        y, target = self._capture(camera, self.tuning, 11)
        gain = tune_nsr((self._spectral(camera, y, g) for g in GAINS), target, n, GAINS)
        nsr = tune_nsr((self._constant(camera, y, k) for k in NSR_GRID), target, n)
        y, target = self._capture(camera, self.scenes, 12)
        return {"spectral_db": score(self._spectral(camera, y, gain), target),
                "constant_db": score(self._constant(camera, y, nsr), target)}


def validate_restorability(out: Path, results: dict) -> tuple[dict, WienerReference]:
    """Predicted against measured over the validation masks; also returns the reference (it scores the
    restorability objective's designs)."""
    from scipy.stats import spearmanr

    from codesign.data.scenes import build_scene_source
    from codesign.data.source import SceneSource
    from codesign.design.restorability import restorability_for

    source = build_scene_source(_cfg([]).data)
    train = source.split_names("train")
    held = SceneSource.from_folder(str(HELD_OUT)) if HELD_OUT.is_dir() else None
    rows, reference = [], None
    for label, mask_cfg, vector in _validation_masks(results, out):
        camera = _camera(mask_cfg, vector)
        if reference is None:  # the spectrum and noise of the prediction, fitted to the training scenes
            module = restorability_for(camera, source.fixed_batch(train, camera.image_size))
            scenes = (held.fixed_batch(held.split_names("all"), camera.scene_size) if held is not None
                      else source.fixed_batch(source.split_names("all"), camera.scene_size))
            reference = WienerReference(module, source.fixed_batch(train, camera.scene_size), scenes)
        kernel = camera.frozen_optics().kernel
        predicted = float(reference.module(kernel))
        variants = {name: float(m(kernel)) for name, m in _variants(reference.module).items()}
        measured = reference(camera)
        with torch.no_grad():
            lsr = float(camera.frozen_optics().state.psf.max()) / camera.system.uncoded_peak
        rows.append({"mask": mask_cfg["kind"], "label": label, "lsr": lsr, "predicted_db": predicted,
                     "edge_lost": float(reference.module.edge_fraction(kernel)), **variants, **measured})
        print(f"  restorability {label}: predicted {predicted:.2f} dB, measured {measured['spectral_db']:.2f} dB "
              f"(constant nsr {measured['constant_db']:.2f} dB)", flush=True)
    pred = [r["predicted_db"] for r in rows]
    return {"rows": rows, "masks": len(rows),
            "scenes": f"{len(reference.scenes)} photographs of {HELD_OUT.name}/" if held is not None
            else f"the {len(reference.scenes)} built-in scenes",
            "spearman": float(spearmanr(pred, [r["spectral_db"] for r in rows]).statistic),
            "spearman_constant_nsr": float(spearmanr(pred, [r["constant_db"] for r in rows]).statistic),
            "spearman_variants": {name: float(spearmanr([r[name] for r in rows], [r["spectral_db"] for r in rows])
                                              .statistic) for name in _variants(reference.module)}}, reference


def _variants(module) -> dict:
    """The prediction with the edge's light costing one scene variance, and without the edge term (circular)."""
    import copy

    one, none = copy.copy(module), copy.copy(module)
    one.edge_cost, none.edge = 1.0, False
    return {"predicted_edge_cost_1_db": one, "predicted_circular_db": none}


def objective_searches(scale: str, out: Path, reference: "WienerReference") -> dict:
    """The restorability objective on the spline family, at the published mask's LSR ceiling (from a 20 rad
    defocus) and at 1e-3 (from 45 rad; the ceiling binds the sampled peak, 0.99e-3 leaves room for the refined
    one); each design's measured Wiener PSNR next to its prediction."""
    res = {}
    for name, ceiling, defocus in (("published", "published", 20), ("1e-3", "0.99e-3", 45)):
        over = ["mask=spline", "mask.init=defocus", f"mask.defocus_rad={defocus}", "search.init=mask",
                "search.objective=restorability", f"search.lsr_ceiling={ceiling}", "search.mtf_floor=null",
                f"search.max_evals={BUDGET[scale]['objective_evals']}", "search.pareto_factors=null"]
        print(f"  restorability objective, LSR ceiling {name}", flush=True)
        res[name] = _search(out / "design" / f"restorability_{name}", over)
        res[name]["measured"] = reference(_camera({"kind": "spline",
                                                   "init": _record(out / "design" / f"restorability_{name}")}))
    res["published mask"] = {"measured": reference(_camera({"kind": "halfring"}))}
    return res


def run(scale: str, out: Path) -> Report:
    t0 = time.perf_counter()
    results, extra = family_searches(scale, out)
    fronts_figure(out / "design_fronts.png", results)
    validation, reference = validate_restorability(out, results)
    objective = objective_searches(scale, out, reference)
    data = {"families": {k: {kk: vv for kk, vv in v.items() if kk not in ("starts",)}
                         for k, v in {**results, **extra}.items()},
            "restorability_validation": validation, "restorability_objective": objective,
            "seconds": time.perf_counter() - t0}
    write_json(out / "design.json", data)
    return report(data, out / "design_fronts.png")


def redo(scale: str, out: Path, families: list[str]) -> Report:
    """Search ``families`` again and validate restorability again (its masks include each family's best); the
    other families, the extra runs and the objective searches (spline only) are kept from ``design.json``."""
    unknown = sorted(set(families) - set(FAMILIES))
    if unknown:
        raise SystemExit(f"--redo {','.join(unknown)}: not a family; allowed: {', '.join(FAMILIES)}")
    path = out / "design.json"
    if not path.is_file():
        raise SystemExit(f"--redo needs an earlier {path}; run python -m benchmarks --only design --scale {scale}")
    data = json.loads(path.read_text())
    t0 = time.perf_counter()
    results, _ = family_searches(scale, out, tuple(families))
    data["families"].update(results)
    core = {fam: data["families"][fam] for fam in FAMILIES}
    fronts_figure(out / "design_fronts.png", core)
    data["restorability_validation"], _ = validate_restorability(out, core)
    data["redone"] = {"families": families, "seconds": time.perf_counter() - t0}
    write_json(path, data)
    return report(data, out / "design_fronts.png")


def report(data: dict, fig: Path) -> Report:
    """The docs section of a design.json (``python -m benchmarks.bench_design --report [--scale S]`` re-renders
    it without searching again)."""
    families, validation, objective = data["families"], data["restorability_validation"], \
        data["restorability_objective"]
    pub = families[FAMILIES[0]]
    rep = Report("design", "Mask design: every family against the physical limit")
    rep.notes.append(
        f"Default optics (384 samples across the aperture, 640-pixel window), MTF floor = the published mask's "
        f"mtf_mean {pub['mtf_mean_published']:.4g} (band {pub['mtf_band_low']:g}..{pub['mtf_band_high']:g} of the "
        f"cutoff), each family's energy floor (the published mask's {pub['window_energy_published']:.3f} for half "
        f"rings, 0.98 for the others). The published mask: LSR {pub['lsr_published']:.4g}, "
        f"{pub['lsr_over_limit_published']:.2f}x the limit, restorability {pub['restorability_published']:.2f} dB. "
        f"LSR is the certified continuous peak; the limit is at each design's own mtf_mean and window energy; "
        f"re-check: the largest deviation of LSR and mtf_mean on a pupil grid twice as fine and a window twice as "
        f"wide (tolerance 2 %).")
    rep.tables.append(markdown_table(
        ["family", "window", "parameters", "evaluations", "seconds", "LSR", "mtf_mean", "window energy", "LSR / limit",
         "restorability dB", f"LSR ({QUANTIZED} levels)", f"restorability dB ({QUANTIZED} levels)", "re-check",
         "feasible"], _family_rows(families), {"seconds": ".0f", "window energy": ".4f", "LSR / limit": ".2f",
                             "restorability dB": ".2f", f"restorability dB ({QUANTIZED} levels)": ".2f"}))
    rep.figures.append(fig)
    vr = validation["rows"]
    rep.notes.append(f"Restorability validated over {validation['masks']} masks: Spearman rank correlation "
                     f"{validation['spearman']:.3f} between the predicted PSNR and the affine-matched PSNR of the "
                     f"tuned classical Wiener filter (the fitted scene spectrum, one tuned noise gain) measured on "
                     f"simulated captures of {validation['scenes']} (figure settings, laser off; tuned on the "
                     f"built-in training scenes); {validation['spearman_constant_nsr']:.3f} against the constant-nsr "
                     f"Wiener filter of the Evaluator. Edge lost: the share of the field's light from beyond its "
                     f"border, which the prediction counts as lost at twice the scene variance; ranked with it at "
                     f"one scene variance: {validation['spearman_variants']['predicted_edge_cost_1_db']:.3f}, "
                     f"without the edge term: {validation['spearman_variants']['predicted_circular_db']:.3f}.")
    rep.tables.append(markdown_table(
        ["mask", "family", "LSR (sampled)", "edge lost", "predicted dB", "measured dB", "measured dB (constant nsr)"],
        [[r["label"], r["mask"], r["lsr"], r["edge_lost"], r["predicted_db"], r["spectral_db"], r["constant_db"]]
         for r in vr], {"edge lost": ".3f", "predicted dB": ".2f", "measured dB": ".2f",
                        "measured dB (constant nsr)": ".2f"}))
    pub_row = objective["published mask"]
    any_obj = objective["published"]
    obj_rows = [["published mask", float(any_obj["lsr_published"]), float(any_obj["mtf_mean_published"]),
                 float(any_obj["restorability_published"]), pub_row["measured"]["spectral_db"],
                 pub_row["measured"]["constant_db"], "-"]]
    obj_rows += [[f"spline, LSR ceiling {k}", float(v["lsr"]), float(v["mtf_mean"]), float(v["restorability"]),
                  v["measured"]["spectral_db"], v["measured"]["constant_db"],
                  "yes" if v["feasible"] else "NO"] for k, v in objective.items() if k != "published mask"]
    rep.notes.append("The restorability objective (maximize the predicted PSNR under an LSR ceiling, no MTF floor; "
                     "measured: the tuned Wiener filters of the validation above on the same scenes).")
    rep.tables.append(markdown_table(
        ["design", "LSR", "mtf_mean", "predicted dB", "measured dB", "measured dB (constant nsr)", "feasible"],
        obj_rows, {"predicted dB": ".2f", "measured dB": ".2f", "measured dB (constant nsr)": ".2f"}))
    return rep


if __name__ == "__main__":
    import sys

    from benchmarks.__main__ import render_section, standalone
    from benchmarks.common import RESULTS, write_text

    scale = sys.argv[sys.argv.index("--scale") + 1] if "--scale" in sys.argv else "quick"
    if "--report" in sys.argv:  # the section of an existing design.json, printed
        print(render_section(report(json.loads((RESULTS / scale / "design.json").read_text()),
                                    RESULTS / scale / "design_fronts.png"), "."))
    elif "--redo" in sys.argv:  # e.g. --redo pixel: those families searched again, the rest kept
        families = sys.argv[sys.argv.index("--redo") + 1].split(",")
        torch.set_num_threads(os.cpu_count() or 1)
        section = render_section(redo(scale, RESULTS / scale, families), ".")
        write_text(RESULTS / scale / "design.md", section)
        print(section)
    else:
        standalone(run)
