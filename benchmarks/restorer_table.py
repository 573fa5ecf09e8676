"""``python -m benchmarks.restorer_table``: every restorer side by side (issue 35 item 5): the paper's SGAN-B, SGAN-E,
SGAN-F, the main job's gated SGAN-B and WienerUNet, each trained from scratch on the same data for the same steps,
then scored on the same photographs with Wiener (tuned per condition) and the sensor image as floors.

Each network: ``+experiment=baseline model=X`` at the main job's sizes (preset=joint_cpu, trainer=joint_cpu: 96 px
padded to 128, batch 4, the cpu width), on one mask (default: the published half rings), seed 0, the same ``--steps``
(the same training images, so the same data); its step time is the run's training seconds over its steps (on 2
threads of a CPU, nothing else running). Then ``python -m benchmarks.pretrained_eval`` on that mask (the 12
photographs of ../shared/data/scenes, never trained on; alpha_l = 0, 1e3, 1e5, 1e6). ``--with-pretrained`` adds the
shipped restorer (trained over a pool of masks, with its own budget: a reference row, not an equal one).
``--restorers sgan_b_l1`` trains the main job's network (not in the default table); with ``--set
init.checkpoint=pretrained`` it adapts the shipped one to ``--mask`` for ``--steps`` (docs/models.md Sec. 14).

Into ``--out``: restorer_table.json (commands, steps, seconds, every figure, machine), restorer_table.md (the table
docs/models.md shows) and each network's weights-only checkpoint. The runs go one after another (two at once on two
cores would make every step time wrong).

    python -m benchmarks.restorer_table --out benchmarks/results/restorers --steps 300
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import keep_weights, machine, mask_overrides, markdown_table, write_json, write_text

ROOT = Path(__file__).resolve().parents[1]
RESTORERS = ("sgan_b", "sgan_e", "sgan_f", "sgan_b_gated", "wiener_unet", "wiener_naf")
ALLOWED = RESTORERS + ("sgan_b_l1",)  # the main job's network: --restorers only, not in the default table
ALPHAS = ("0", "1e3", "1e5", "1e6")


def train_command(model: str, a, run: Path) -> list[str]:
    return [sys.executable, "-m", "codesign", "+experiment=baseline", f"model={model}", "preset=joint_cpu",
            "trainer=joint_cpu", f"trainer.steps={a.steps}", f"data.batch_size={a.batch}", f"seed={a.seed}",
            f"threads={a.threads}", "device=cpu", *mask_overrides(a.mask), f"trainer.val_every={a.steps}",
            "trainer.image_every=0", f"trainer.checkpoint_every={a.steps}", "evaluate.laser_strengths=[0]",
            "evaluate.stages=[]", "evaluate.max_scenes=1", "logging.tensorboard=false", f"hydra.run.dir={run}",
            *a.set]


def run(cmd: list[str], log: Path) -> None:
    with open(log, "w") as f:
        rc = subprocess.run(cmd, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT).returncode
    if rc:
        raise SystemExit(f"{' '.join(cmd[1:])} failed ({rc}); its log: {log}\n" + log.read_text()[-3000:])


def evaluate(checkpoint: str, a, work: Path, name: str) -> dict:
    out = work / f"eval_{name}.json"
    run([sys.executable, "-m", "benchmarks.pretrained_eval", "--checkpoint", checkpoint, "--masks", a.mask,
         "--threads", str(a.threads), "--out", str(out)], work / f"eval_{name}.log")
    return json.loads(out.read_text())["masks"][a.mask]


def table(rows: dict, times: dict | None = None) -> str:
    """One line per restorer: PSNR after the gain/offset match (its gain over Wiener +- 95 %) per alpha_l, plain
    PSNR and SSIM at 0 and 1e6, the step time (``times``: seconds per step measured apart, by name); the floors
    (Wiener, sensor) from the first restorer's evaluation (they do not depend on the network)."""
    times = times or {}
    if not any("eval" in r for r in rows.values()):  # --no-eval: the step times alone
        return markdown_table(["restorer", "steps", "s / step"],
                              [[n, r["steps"], f"{r['seconds'] / r['steps']:.2f}"] for n, r in rows.items()])
    first = next(iter(rows.values()))["eval"]["alpha"]
    head = ["restorer", "steps", "s / step", *(f"alpha_l {x}" for x in ALPHAS), "plain PSNR / SSIM at 0",
            "at 1e6"]
    body = []
    for floor in ("sensor", "wiener"):
        body.append([floor, "", "", *(f"{first[x][floor]['psnr_matched']:.2f}" for x in ALPHAS),
                     *(f"{first[x][floor]['psnr']:.2f} / {first[x][floor]['ssim']:.3f}" for x in ("0", "1e6"))])
    for name, r in rows.items():
        al = r["eval"]["alpha"]
        gains = [f"{al[x]['sgan']['psnr_matched']:.2f} ({al[x]['gain_over_wiener']['mean']:+.2f} +- "
                 f"{al[x]['gain_over_wiener']['interval']:.2f})" for x in ALPHAS]
        step = times.get(name, r["seconds"] / r["steps"] if r.get("steps") and r.get("seconds") else None)
        step = "n/a" if step is None else f"{step:.2f}"
        body.append([name, r.get("steps", "n/a"), step, *gains,
                     *(f"{al[x]['sgan']['psnr']:.2f} / {al[x]['sgan']['ssim']:.3f}" for x in ("0", "1e6"))])
    return markdown_table(head, body)


def step_times(path: Path | None) -> dict:
    """name -> seconds per step of a --no-eval run's restorer_table.json (none: {})."""
    if path is None:
        return {}
    rows = json.loads(path.read_text())["rows"]
    return {n: r["seconds"] / r["steps"] for n, r in rows.items() if r.get("steps")}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--mask", default="published", help="published, or the path of a mask record")
    p.add_argument("--restorers", default=",".join(RESTORERS))
    p.add_argument("--with-pretrained", action="store_true", help="add the shipped restorer as a reference row")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a further override of every training (repeatable), e.g. --set model.target_level=exposure")
    p.add_argument("--no-eval", action="store_true", help="train and time only (a clean step-time run)")
    p.add_argument("--times", type=Path, help="a --no-eval run's restorer_table.json: the step-time column from it")
    p.add_argument("--render", type=Path, help="train nothing: write the table of this restorer_table.json again "
                   "(with --times) into --out")
    a = p.parse_args(argv)
    if a.render is not None:
        text = table(json.loads(a.render.read_text())["rows"], step_times(a.times))
        print(text)
        write_text(a.out / "restorer_table.md", text + "\n")
        return 0
    names = [r.strip() for r in a.restorers.split(",") if r.strip()]
    unknown = sorted(set(names) - set(ALLOWED))
    if unknown or not names:
        p.error(f"--restorers: unknown {unknown or 'none given'}; allowed: {', '.join(ALLOWED)}")
    if a.mask != "published" and not Path(a.mask).is_file():
        p.error(f"--mask: {a.mask!r} is neither 'published' nor a mask record file")
    if a.steps < 1:
        p.error(f"--steps: {a.steps} must be >= 1")
    if a.times is not None and not a.times.is_file():
        p.error(f"--times: no file {a.times}")
    work = Path(tempfile.mkdtemp(prefix="codesign_restorer_table_"))
    a.out.mkdir(parents=True, exist_ok=True)
    record = {"machine": machine(), "args": {k: str(v) for k, v in vars(a).items()}, "rows": {}}
    for name in names:
        t0, rundir = time.perf_counter(), work / name
        cmd = train_command(name, a, rundir)
        print(f"training {name}: {' '.join(cmd[1:])}", flush=True)
        run(cmd, work / f"{name}.log")
        m = json.loads((rundir / "metrics.json").read_text())
        row = {"command": "python " + " ".join(cmd[1:]).replace(str(work), "RUN"), "steps": m["steps"],
               "seconds": round(m["seconds"], 1), "parameters_generators": m.get("parameters_generators"),
               "wall_s": round(time.perf_counter() - t0, 1),
               **keep_weights(rundir / "checkpoint.pt", a.out / f"{name}.pt")}
        if not a.no_eval:
            row["eval"] = evaluate(str(a.out / f"{name}.pt"), a, work, name)
        record["rows"][name] = row
        print(f"{name}: {row['steps']} steps, {row['seconds'] / row['steps']:.2f} s/step", flush=True)
    if a.with_pretrained and not a.no_eval:
        record["rows"]["shipped (pool, own budget)"] = {"eval": evaluate("pretrained", a, work, "pretrained")}
    text = table(record["rows"], step_times(a.times))
    print(text, flush=True)
    write_json(a.out / "restorer_table.json", record)
    write_text(a.out / "restorer_table.md", text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
