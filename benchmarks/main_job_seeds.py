"""The main job over seeds: does the co-design protocol of ``python -m codesign +experiment=joint`` meet its goal in
every seed, and does its joint stage add more than the seed-to-seed spread (issue 36: at least +0.5 dB over the
frozen designed mask at alpha_l = 1e6, beyond twice the spread, 3 seeds)?

    python -m benchmarks.main_job_seeds --out /tmp/seeds                        # seeds 0 1 2, ~15 min each on 2 cores
    python -m benchmarks.main_job_seeds --out /tmp/eighth --set codesign.lsr_max=published/8
    python -m benchmarks.main_job_seeds --out /tmp/t --runs RUN0 RUN1 RUN2      # tabulate finished runs only

Each seed runs in OUT/seed<k> (the main job's own folder: a killed seed continues stage by stage, a finished one,
its metrics.json written, is not run again). OUT/seeds.json and OUT/seeds.md: per seed the LSR against the
published mask, the total gain and the joint stage's gain (PSNR after the gain/offset match, mean over the held-out
photographs +- the 95 % interval of the per-scene differences); over the seeds their mean and standard deviation,
and the joint stage's verdict (paired_gain in benchmarks/common.py: the seed spread is the larger standard deviation
over seeds of the two systems compared).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

from benchmarks.common import JOINT_GOAL_DB, REPO, Runner, machine, markdown_table, paired_gain, write_json, write_text
from codesign.train.protocol_summary import GAINS

ALPHAS = ("0", "1e3", "1e6")
TOTAL = GAINS[-1][0]  # the summary's rows (codesign/train/protocol_summary.py): the total ...
JOINT = next(label for label, *_ in GAINS if label.startswith("joint stage"))  # ... and the joint stage
# the settings every run of one table must share (a spread over seeds of different settings is no spread)
SHARED = ("lsr_max_from", "network", "trainer_steps", "finetune_steps", "scenes")


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.main_job_seeds", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="folder of the seeds' runs and of seeds.json / seeds.md")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="the main job's seed= values")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="an override of every seed's main job (e.g. codesign.lsr_max=published/8)")
    ap.add_argument("--runs", type=Path, nargs="+", default=None,
                    help="run nothing: tabulate these finished main-job folders (each with its metrics.json)")
    args = ap.parse_args(argv)
    problems = []
    for item in args.set:
        if "=" not in item or item.startswith("="):
            problems.append(f"--set {item!r}: must be KEY=VALUE")
        elif item.split("=", 1)[0].lstrip("+~") in ("seed", "hydra.run.dir"):
            problems.append(f"--set {item!r}: the seed and the run folder are set per seed (--seeds, --out)")
    if args.runs is not None:
        if args.set:
            problems.append("--set: has no effect with --runs (the runs are finished)")
        for run in args.runs:
            if not (run / "metrics.json").is_file():
                problems.append(f"--runs {run}: no metrics.json (not a finished main-job folder)")
    elif len(set(args.seeds)) != len(args.seeds):
        problems.append(f"--seeds {args.seeds}: each seed once")
    if len(args.runs or args.seeds) < 2:
        problems.append("a spread over seeds needs at least 2 runs (issue 36 asks for 3)")
    if problems:
        ap.error("; ".join(problems))
    return args


def load_runs(paths: list[Path]) -> dict[int, dict]:
    """seed -> the main job's metrics.json, after checking that the runs are main jobs of one setting and
    different seeds."""
    runs = {}
    for path in paths:
        m = json.loads((path / "metrics.json").read_text())
        if m.get("protocol") != "codesign":
            raise SystemExit(f"main_job_seeds: {path} is not a main job (protocol {m.get('protocol')!r}, "
                             "expected 'codesign')")
        if m["seed"] in runs:
            raise SystemExit(f"main_job_seeds: seed {m['seed']} twice (the second in {path})")
        shown = path.resolve()
        runs[m["seed"]] = {**m, "run_dir": str(shown.relative_to(REPO) if shown.is_relative_to(REPO) else shown)}
    first = next(iter(runs.values()))
    for seed, m in runs.items():
        differ = [k for k in SHARED if m.get(k) != first.get(k)]
        if differ:
            raise SystemExit(f"main_job_seeds: seed {seed} differs from seed {first['seed']} in {differ}: "
                             "the runs must share every setting but the seed")
    return dict(sorted(runs.items()))


def per_seed_row(m: dict) -> dict:
    """One seed's figures: LSR ratio, the totals and the joint stage's gains (mean and interval) at every
    alpha_l, the two systems the joint stage compares, the goal."""
    row = {"minutes": m["minutes"], "lsr_ratio": m["masks"]["co-designed"]["lsr"] / m["lsr_published_peak"],
           "goal_met": bool(m["goal"]["met"])}
    for alpha in ALPHAS:
        cond = f"laser_{alpha}"
        for name, key in (("total", TOTAL), ("joint", JOINT)):
            row[f"{name}_{alpha}"] = m["gains"][key][cond]["mean"]
            row[f"{name}_{alpha}_interval"] = m["gains"][key][cond]["interval"]
        for system in ("codesigned_network", "designed_network"):
            row[f"{system}_{alpha}"] = m["systems"][system][cond]["psnr_matched"]
    return row


def summarize(rows: dict[int, dict]) -> dict:
    """Mean and standard deviation over seeds of every figure; the joint stage at every alpha_l read as the study
    reads an arm against its frozen arm (paired_gain); the goals."""
    keys = [k for k, v in next(iter(rows.values())).items() if isinstance(v, float)]
    over = {k: {"mean": statistics.mean(r[k] for r in rows.values()),
                "std": statistics.stdev(r[k] for r in rows.values())} for k in keys}
    joint = {alpha: paired_gain({s: {"v": r[f"codesigned_network_{alpha}"]} for s, r in rows.items()},
                                {s: {"v": r[f"designed_network_{alpha}"]} for s, r in rows.items()}, "v")
             for alpha in ALPHAS}
    j = joint["1e6"]
    return {"over_seeds": over, "joint_vs_frozen": joint,
            "main_job_goal_every_seed": all(r["goal_met"] for r in rows.values()),
            "joint_goal_met": j["gain"] >= JOINT_GOAL_DB and j["significant"]}


def render(res: dict) -> str:
    rows, s = res["rows"], res["summary"]

    def fmt(v: float, interval: float) -> str:
        return f"{v:+.2f} +- {interval:.2f}"

    header = ["seed", "minutes", "co-designed / published LSR", *(f"total {a}" for a in ALPHAS),
              *(f"joint stage {a}" for a in ALPHAS), "goal"]
    table = [[seed, f"{r['minutes']:.1f}", f"{r['lsr_ratio']:.3f}",
              *(fmt(r[f"total_{a}"], r[f"total_{a}_interval"]) for a in ALPHAS),
              *(fmt(r[f"joint_{a}"], r[f"joint_{a}_interval"]) for a in ALPHAS), "met" if r["goal_met"] else "missed"]
             for seed, r in rows.items()]
    o = s["over_seeds"]
    table.append(["mean +- sd over seeds", f"{o['minutes']['mean']:.1f}", f"{o['lsr_ratio']['mean']:.3f}",
                  *(f"{o[f'total_{a}']['mean']:+.2f} +- {o[f'total_{a}']['std']:.2f}" for a in ALPHAS),
                  *(f"{o[f'joint_{a}']['mean']:+.2f} +- {o[f'joint_{a}']['std']:.2f}" for a in ALPHAS), ""])
    j = s["joint_vs_frozen"]["1e6"]
    lines = [f"# The main job over {len(rows)} seeds", "",
             f"`{res['command']}`; {res['date']}; {res['machine_line']}; settings: {res['settings']}", "",
             ("PSNR after the gain/offset match [dB] at alpha_l = 0, 1e3, 1e6, on the held-out photographs; per seed "
             "the mean over the scenes +- the 95 % interval of the per-scene differences."), "",
             markdown_table(header, table), "",
             f"- main-job goal met in every seed: {'yes' if s['main_job_goal_every_seed'] else 'no'}",
             (f"- joint stage at alpha_l = 1e6 (co-designed - designed, both + network, paired by seed): "
             f"{j['gain']:+.2f} dB, paired sd {j['gain_std']:.2f}, seed spread {j['spread']:.2f} (the larger sd of "
             f"the two systems); goal (>= +{JOINT_GOAL_DB} dB and beyond twice the spread): "
             f"{'met' if s['joint_goal_met'] else 'not met'}")]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    args = parse_args(argv)
    out = args.out.resolve()
    t0 = time.perf_counter()
    if args.runs is None:
        run = Runner({"main job": len(args.seeds)}, "main_job_seeds")
        paths = []
        for seed in args.seeds:
            run_dir = out / f"seed{seed}"
            run("main job", f"main job, seed {seed}", run_dir,
                ["+experiment=joint", *args.set, f"seed={seed}"], timeout=4 * 3600)
            paths.append(run_dir)
    else:
        paths = [p.resolve() for p in args.runs]
    runs = load_runs(paths)
    rows = {seed: per_seed_row(m) for seed, m in runs.items()}
    mach = machine()
    res = {"command": "python -m benchmarks.main_job_seeds " + " ".join(argv if argv is not None else sys.argv[1:]),
           "date": time.strftime("%Y-%m-%d"), "machine": mach,
           "machine_line": ", ".join(f"{k} {v}" for k, v in mach.items() if k != "date"),
           "settings": {k: next(iter(runs.values())).get(k) for k in SHARED if k != "scenes"},
           "runs": {str(s): m["run_dir"] for s, m in runs.items()},
           "minutes_this_invocation": (time.perf_counter() - t0) / 60,
           "rows": rows, "summary": summarize(rows)}
    res["markdown"] = render(res)  # as seeds.md: what docs quote (benchmarks/doc_figures.py)
    write_json(out / "seeds.json", res)
    write_text(out / "seeds.md", res["markdown"])
    print(res["markdown"], end="")
    print(f"wrote {out / 'seeds.md'} and seeds.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
