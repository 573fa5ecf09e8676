"""The co-design study: does a jointly trained mask + network beat the published mask at the same budget, by more
than the spread between seeds?

Protocol (docs/codesign.md, Sec. 7):
  1. for every seed, pretrain one network on the published mask (``+experiment=joint codesign.mask_lr=0``: the
     joint code path with the mask frozen), by default on the reconstruction terms alone (model.loss.adv = mdf = 0:
     the GAN practice of ESRGAN / BasicSR, and what a short CPU budget can teach);
  2. from that seed's checkpoint (``init.checkpoint``), fine-tune with the same steps, data and objective:
       published (frozen)        the control arm
       joint from published      the mask learns, under the published mask's smooth LSR
       NAME (frozen)             a searched design (``--design NAME=RECORD``), the network adapts to it
       joint from NAME           the design learns too, under its own smooth LSR (codesign.lsr_max=start)
  3. evaluate every fine-tuned system on held-out scenes: the built-in test split (the joint run's own
     evaluation) and every photograph of ``--scenes`` (``+experiment=evaluate evaluate.split=all``), at
     alpha_l = 0, 1e3, 1e6, with the sensor image and classical Wiener as floors;
  4. write study.json, study.md and psnr_vs_lsr.png: per arm the mean and standard deviation over seeds, and
     whether its gain over the frozen published arm (paired by seed) exceeds twice the seed spread.

    python -m benchmarks.codesign_study                                  # the CPU study, ~1 h on 2 cores
    python -m benchmarks.codesign_study --smoke --out /tmp/study         # every step at smoke size, ~3 min

The main job's own protocol (design, restorer, its joint arm against its frozen designed arm) over seeds is
benchmarks/main_job_seeds.py.

Every run lives in OUT/runs/<arm>/seed<k>; a run whose metrics.json exists is not run again, so a killed study
continues where it stopped (delete a run's folder to redo it).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

from benchmarks.common import (JOINT_GOAL_DB, REPO, Runner, machine, markdown_table, paired_gain, write_json,
                               write_text)

RESULTS = REPO / "benchmarks" / "results" / "codesign_study"
SCENES = REPO.parent / "shared" / "data" / "scenes"
DESIGNS = REPO / "benchmarks" / "results" / "full" / "design"
DEFAULT_DESIGNS = (f"spiral={DESIGNS / 'spiral' / 'best_mask.json'}", f"spline={DESIGNS / 'spline' / 'best_mask.json'}")
ALPHAS = ("0", "1e3", "1e6")
METRICS = ("psnr", "ssim", "psnr_matched")
OBJECTIVES = {"recon": ["model.loss.adv=0", "model.loss.mdf=0"], "full": []}
# the study's protocol: every arm scored on the data source's test split (built-in: 2 scenes) and the photographs
# of --scenes, as measured in docs/codesign.md Sec. 7 (not the shipped held-out set, evaluate.scenes=heldout)
EVALUATE = ["evaluate.laser_strengths=[0,1.0e3,1.0e6]", "evaluate.stages=[]", "evaluate.scenes=data"]
SMOKE = ["debug=smoke", "evaluate.tuning_size=2"]
REFERENCE = "published (frozen)"


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.codesign_study", description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="fine-tuning seeds (>= 3 for a spread)")
    ap.add_argument("--pretrain-steps", type=int, default=300, help="steps of the published-mask pretraining")
    ap.add_argument("--steps", type=int, default=80, help="fine-tuning steps of every arm")
    ap.add_argument("--design", action="append", default=None, metavar="NAME=RECORD",
                    help="a searched mask's record (best_mask.json); default: the spiral and spline designs of "
                         "benchmarks/results/full/design")
    ap.add_argument("--objective", choices=sorted(OBJECTIVES), default="recon",
                    help="recon: reconstruction terms only (default); full: the variant's whole GAN objective")
    ap.add_argument("--scenes", type=Path, default=SCENES, help="held-out photographs (every one is evaluated)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--smoke", action="store_true", help="every step at smoke size (a check, not a result)")
    ap.add_argument("--render", action="store_true", help="run nothing: rewrite OUT/study.md from OUT/study.json")
    args = ap.parse_args(argv)
    if args.render:
        if not (args.out / "study.json").is_file():
            ap.error(f"--render: no {args.out / 'study.json'} to render")
        return args
    args.design = args.design or list(DEFAULT_DESIGNS)
    problems = []
    if len(set(args.seeds)) < 2:
        problems.append("--seeds: give at least 2 different seeds (a spread needs them; the study's default is 3)")
    for key in ("pretrain_steps", "steps"):
        if getattr(args, key) < 1:
            problems.append(f"--{key.replace('_', '-')} {getattr(args, key)}: must be >= 1")
    designs = {}
    for item in args.design:
        name, _, record = item.partition("=")
        path = Path(record).expanduser()
        if not name or not record or not name.replace("_", "").isalnum():
            problems.append(f"--design {item!r}: must be NAME=RECORD (NAME letters, digits and _)")
        elif not path.is_file():
            problems.append(f"--design {item!r}: no such record file")
        else:
            try:
                kind = json.loads(path.read_text())["kind"]
            except (ValueError, KeyError, TypeError):
                problems.append(f"--design {item!r}: not a mask record (a JSON object with a 'kind')")
                continue
            designs[name] = (path.resolve(), kind)
    if not args.scenes.is_dir():
        problems.append(f"--scenes {args.scenes}: no such folder of photographs")
    if problems:
        ap.error("; ".join(problems))
    args.designs = designs
    if args.smoke:  # smoke: a check of the plumbing, at the smoke config's 4 steps unless asked otherwise
        args.pretrain_steps, args.steps = min(args.pretrain_steps, 4), min(args.steps, 4)
    return args


def arms(designs: dict) -> dict[str, list[str]]:
    """Arm name -> the joint-run overrides that make it (besides the common ones)."""
    out = {REFERENCE: ["codesign.mask_lr=0"], "joint from published": []}
    for name, (record, kind) in designs.items():
        start = [f"mask={kind}", f"mask.init={record}", "codesign.lsr_max=start"]
        out[f"{name} (frozen)"] = start + ["codesign.mask_lr=0"]
        out[f"joint from {name}"] = start
    return out


def folder(arm: str) -> str:
    return arm.replace(" (frozen)", "_frozen").replace("joint from ", "joint_").replace(" ", "_")


def network_column(metrics: dict) -> str:
    """The restorer's column of an evaluation table (the others are the floors)."""
    columns = set(next(iter(metrics["evaluation"].values()))) - {"sensor", "wiener", "g1_wiener"}
    if len(columns) != 1:
        raise SystemExit(f"codesign_study: cannot tell the network's column among {sorted(columns)}")
    return columns.pop()


def held_out(builtin: dict, photos: dict, method: str) -> dict:
    """Scene-weighted means over the built-in test split (the joint run's evaluation) and the photographs (the
    evaluate run's): ``{method}_{metric}_{alpha}`` for the network, the sensor image and Wiener."""
    nb, npho = len(builtin["evaluation_scenes"]), len(photos["evaluation_scenes"])
    out = {"scenes": nb + npho}
    for alpha in ALPHAS:
        cond = f"laser_{alpha}"
        for m_name, column in (("net", method), ("sensor", "sensor"), ("wiener", "wiener")):
            for metric in METRICS:
                a = builtin["evaluation"][cond][column][metric]
                b = photos["evaluation"][cond][column][metric]
                out[f"{m_name}_{metric}_{alpha}"] = (nb * a + npho * b) / (nb + npho)
    return out


def recheck(record: Path) -> dict:
    """The learned mask (its record) re-evaluated where the training could not cheat: a pupil grid twice as fine
    and a window twice as wide (codesign.design.check.verify_design): its largest relative change of LSR or
    mtf_mean, and whether that is within the 2 % tolerance."""
    import torch

    from codesign.design.check import verify_design
    from codesign.design.merit import MetricsSpec
    from codesign.optics import OpticsSpec, PupilGrid, build_mask

    rec = json.loads(record.read_text())
    spec = OpticsSpec(**rec["optics"])
    grid = PupilGrid.from_spec(spec, torch.float32, torch.device("cpu"))
    mask = build_mask({"kind": rec["kind"], "init": str(record)}, grid, spec.aperture_diameter_m)
    check = verify_design(mask.freeze(), spec, MetricsSpec().mtf_band, MetricsSpec().recheck_tolerance)
    return {"recheck_deviation": check["max_deviation"], "recheck_agree": float(check["agree"]),
            "window_energy_whole": check["whole"]["window_energy"]}


def summarize(per_run: dict[str, dict[int, dict]]) -> dict:
    """Per arm: mean and sample standard deviation over seeds of every figure, and (paired_gain) its gain over the
    frozen published arm."""
    ref = per_run[REFERENCE]
    out = {}
    for arm, seeds in per_run.items():
        keys = [k for k in next(iter(seeds.values())) if isinstance(next(iter(seeds.values()))[k], (int, float))]
        row = {}
        for k in keys:
            vals = [seeds[s][k] for s in sorted(seeds)]
            row[k] = {"mean": statistics.mean(vals), "std": statistics.stdev(vals) if len(vals) > 1 else 0.0}
            if arm != REFERENCE:
                row[k].update(paired_gain(seeds, ref, k))
        out[arm] = row
    return out


def goal_met(summary: dict) -> dict[str, bool]:
    """Per arm: LSR at most half the frozen published arm's and the PSNR matched gain at alpha_l = 1e6 positive and
    beyond twice the seed spread."""
    ref_lsr = summary[REFERENCE]["lsr"]["mean"]
    out = {}
    for arm, row in summary.items():
        if arm == REFERENCE:
            continue
        g = row["net_psnr_matched_1e6"]
        out[arm] = row["lsr"]["mean"] <= 0.5 * ref_lsr and g["gain"] > 0 and g["significant"]
    return out


def joint_vs_frozen(per_run: dict[str, dict]) -> dict[str, dict]:
    """Per start (published, every design): its joint arm against its frozen arm (paired_gain) in the network's PSNR
    matched at every alpha_l, and the joint stage's goal (>= +0.5 dB at alpha_l = 1e6 and significant)."""
    out = {}
    for arm, seeds in per_run.items():
        if not arm.startswith("joint from "):
            continue
        start = arm[len("joint from "):]
        frozen = per_run[REFERENCE if start == "published" else f"{start} (frozen)"]
        row = {alpha: paired_gain(seeds, frozen, f"net_psnr_matched_{alpha}") for alpha in ALPHAS
               if f"net_psnr_matched_{alpha}" in next(iter(seeds.values()))}
        row["goal_met"] = row["1e6"]["gain"] >= JOINT_GOAL_DB and row["1e6"]["significant"]
        out[start] = row
    return out


def figure(per_run: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from codesign.io.files import save_figure

    fig, ax = plt.subplots(figsize=(7, 4.5))
    markers = "os^vDP*X"
    for i, (arm, seeds) in enumerate(per_run.items()):
        xs = [v["lsr"] for v in seeds.values()]
        ys = [v["net_psnr_matched_1e6"] for v in seeds.values()]
        ax.scatter(xs, ys, marker=markers[i % len(markers)], s=40, label=arm)
    ax.set_xscale("log")
    ax.set_xlabel("LSR (continuous peak / uncoded peak), lower protects more")
    ax.set_ylabel("PSNR after gain/offset match at alpha_l = 1e6 [dB]")
    ax.set_title("co-design study: every arm and seed (held-out scenes)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(path, fig)


def _arm_order(arm: str) -> tuple:
    """The published arms first, then each design's frozen arm before its joint arm (study.json's keys are sorted)."""
    start = arm[len("joint from "):] if arm.startswith("joint from ") else arm.replace(" (frozen)", "")
    return (start != "published", start, arm.startswith("joint from "))


def render(res: dict, fig_name: str) -> str:
    res = {**res, "summary": dict(sorted(res["summary"].items(), key=lambda kv: _arm_order(kv[0]))),
           "runs": dict(sorted(res["runs"].items(), key=lambda kv: _arm_order(kv[0])))}
    s, m = res["settings"], res["machine"]
    lines = [f"# Co-design study ({'smoke: not a result' if s['smoke'] else 'CPU budget'})", "",
             f"Command: `{res['command']}`; {m.get('cpu', '?')}, {m.get('threads', '?')} threads, torch "
             f"{m.get('torch', '?')}, Python {m.get('python', '?')}; {res['date']}; {res['minutes']:.1f} min of runs.",
             f"Pretraining: {s['pretrain_steps']} steps on the published mask per seed; fine-tuning: {s['steps']} "
             f"steps per arm; objective: {s['objective']}; seeds {s['seeds']}; held-out scenes: {res['scenes']} "
             f"(built-in test split + {s['scenes']}).", "",
             "Mean +- standard deviation over seeds. In brackets: the gain against the frozen published arm, paired "
             "by seed, +- the standard deviation of the paired gains; **bold** when the gain exceeds twice the seed "
             "spread (the larger standard deviation of the two arms, the stricter reading). LSR, mtf_mean "
             "and LSR / limit: the training optics, certified continuous peak; re-check: the largest relative "
             "change of LSR or mtf_mean on a pupil grid twice as fine and a window twice as wide (a design counts "
             "when <= 0.02).", ""]
    cols = [("lsr", ".3g"), ("mtf_mean", ".4f"), ("lsr_over_limit", ".2f"), ("recheck_deviation", ".3f")] + \
        [(f"net_{k}_{a}", ".2f" if "psnr" in k else ".3f") for a in ALPHAS for k in METRICS]
    names = {"psnr": "PSNR", "ssim": "SSIM", "psnr_matched": "PSNR matched"}
    header = ["arm", "LSR", "mtf_mean", "LSR / limit", "re-check"] + [f"{names[k]} {a}" for a in ALPHAS
                                                                      for k in METRICS]
    rows = []
    for arm, row in res["summary"].items():
        cells = [arm]
        for k, fmt in cols:
            v = row[k]
            cell = f"{v['mean']:{fmt}} +- {v['std']:{fmt}}"
            if "gain" in v and k.startswith("net_psnr"):
                g = f"{v['gain']:+.2f}"
                cell += f" ({'**' + g + '**' if v['significant'] else g} +- {v['gain_std']:.2f})"
            cells.append(cell)
        rows.append(cells)
    met = goal_met(res["summary"])
    lines += [markdown_table(header, rows), "", "Goal (LSR <= half the published mask's, PSNR matched at 1e6 ahead of "
              "the frozen published arm by more than twice the seed spread): " + (
                  "met by " + ", ".join(a for a, ok in met.items() if ok) if any(met.values()) else "met by no arm")
              + ".", "", "Floors: the sensor image and classical Wiener on the same scenes "
              "(they depend on the mask; mean over seeds):", ""]
    floor_rows = []
    for arm, row in res["summary"].items():
        floor_rows.append([arm] + [f"{row[f'{w}_psnr_matched_{a}']['mean']:.2f}" for w in ("sensor", "wiener")
                                   for a in ALPHAS])
    lines += [markdown_table(["arm"] + [f"{w} PSNR matched {a}" for w in ("sensor", "Wiener") for a in ALPHAS],
                             floor_rows), ""]
    jvf = joint_vs_frozen({arm: {int(k): v for k, v in seeds.items()} for arm, seeds in res["runs"].items()})
    if jvf:
        lines += ["The joint stage: each joint arm against its own frozen arm (same start, steps, data and seed), "
                  "paired by seed: mean gain +- the standard deviation of the paired gains; **bold** beyond twice "
                  f"the seed spread. Goal: >= +{JOINT_GOAL_DB} dB at alpha_l = 1e6, beyond twice the spread.", "",
                  markdown_table(["joint arm - frozen arm"] + [f"PSNR matched {a}" for a in ALPHAS] +
                                 ["seed spread 1e6", "goal"],
                                 [[f"joint from {start} - {start} (frozen)"] + [
                                     (f"**{row[a]['gain']:+.2f}**" if row[a]["significant"]
                                      else f"{row[a]['gain']:+.2f}")
                                     + f" +- {row[a]['gain_std']:.2f}" for a in ALPHAS]
                                  + [f"{row['1e6']['spread']:.2f}", "met" if row["goal_met"] else "not met"]
                                  for start, row in jvf.items()]), ""]
    lines += [f"![PSNR matched at 1e6 against LSR]({fig_name})", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse_args(argv)
    out = args.out.resolve()
    if args.render:
        res = json.loads((out / "study.json").read_text())
        write_text(out / "study.md", render(res, "psnr_vs_lsr.png"))
        print(f"wrote {out / 'study.md'} from study.json")
        return 0
    runs = out / "runs"
    t0 = time.perf_counter()
    common = ["+experiment=joint", "codesign.protocol=single", "codesign.compare_published=false",
              "logging.tensorboard=false",
              *OBJECTIVES[args.objective], *EVALUATE, *(SMOKE if args.smoke else [])]
    plan = arms(args.designs)
    n = len(args.seeds)
    run = Runner({"pretrain": n, "fine-tune": len(plan) * n, "evaluate": len(plan) * n})
    per_run: dict[str, dict[int, dict]] = {}
    for seed in args.seeds:
        # each seed pretrains its own network (initial weights, data draws, noise): the spread between seeds is
        # then the whole pipeline's, not only the fine-tuning's
        pre_dir = runs / "pretrain" / f"seed{seed}"
        run("pretrain", f"pretraining on the published mask, seed {seed}", pre_dir,
            [*common, "codesign.mask_lr=0", f"trainer.steps={args.pretrain_steps}", f"seed={seed}",
             "init.checkpoint=null"])  # from fresh weights, as the recorded study (joint's default is auto)
        checkpoint = pre_dir / "checkpoint.pt"
        for arm, overrides in plan.items():
            run_dir = runs / folder(arm) / f"seed{seed}"
            joint = run("fine-tune", f"{arm}, seed {seed}", run_dir,
                        [*common, *overrides, f"init.checkpoint={checkpoint}", f"trainer.steps={args.steps}",
                         f"seed={seed}"])
            photos = run("evaluate", f"{arm}, seed {seed}: photographs", run_dir / "photographs",
                         ["+experiment=evaluate", f"checkpoint={run_dir / 'checkpoint.pt'}", "data.scenes=folder",
                          f"data.folder={args.scenes.resolve()}", "evaluate.scenes=data", "evaluate.split=all",
                          "evaluate.max_scenes=1000",
                          *EVALUATE, *(SMOKE if args.smoke else []), f"seed={seed}", "logging.tensorboard=false"])
            per_run.setdefault(arm, {})[seed] = {
                "lsr": joint["lsr"], "mtf_mean": joint["mtf_mean"], "lsr_over_limit": joint["lsr_over_limit"],
                **held_out(joint, photos, network_column(joint)), **recheck(run_dir / "learned_mask.json")}
    res = {"command": "python -m benchmarks.codesign_study " + " ".join(argv if argv is not None else sys.argv[1:]),
           "machine": machine(), "date": time.strftime("%Y-%m-%d"), "minutes": run.spent / 60,
           "minutes_this_invocation": (time.perf_counter() - t0) / 60,
           "settings": {"seeds": args.seeds, "pretrain_steps": args.pretrain_steps, "steps": args.steps,
                        "objective": args.objective, "smoke": args.smoke, "scenes": str(args.scenes),
                        "designs": {k: str(v[0]) for k, v in args.designs.items()}},
           "scenes": next(iter(next(iter(per_run.values())).values()))["scenes"],
           "runs": {arm: {str(s): v for s, v in seeds.items()} for arm, seeds in per_run.items()},
           "summary": summarize(per_run)}
    out.mkdir(parents=True, exist_ok=True)
    fig = figure(per_run, out / "psnr_vs_lsr.png")
    write_json(out / "study.json", res)
    write_text(out / "study.md", render(res, fig.name))
    print(f"wrote {out / 'study.md'}, study.json, {fig.name} ({res['minutes']:.1f} min)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
