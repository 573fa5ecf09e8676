"""``python -m benchmarks.pretrain``: train the shipped restorer (codesign/models/pretrained/) and its controls.

Three trainings of the main job's network (model=sgan_b_l1 with the main job's log-spaced training lasers, at its
sizes, preset=joint_cpu: 96 px padded to 128; the shipped weights also started from 6,400 steps on the published
mask: ``--set init.checkpoint=PATH``, their model card), run side by side on one device (a GPU step of this small
network is launch-bound, so three processes cost little more than one):

- ``pool_seed0`` and ``pool_seed1``: over the mask pool POOL (data.masks: the published half rings, two searched
  spline designs at 1/2 and 1/8 of the published mask's certified peak, three defocus surfaces, and random draws
  around each), seeds 0 and 1: the shipped restorer and its second seed;
- ``single``: the same network, steps and batch on the held-out mask alone (HELDOUT_MASK: the spline design at 1/4
  of the published peak, the main job's ceiling, never in the pool): the control of "one restorer for any mask".

Each run is ``+experiment=baseline`` (its own evaluation on the built-in test split is kept short: the verdict is
benchmarks/pretrained_eval.py's, on the 12 photographs of ../shared/data/scenes, on a CPU). Into ``--out``:
pretrain.json (commands, steps, seconds, device and versions), pretrain.log (every run's log) and each run's
weights-only checkpoint (<run>.pt, about 10 MiB). ``--dry-run`` rehearses it on a CPU at tiny sizes.
``--fit-level CKPT`` trains nothing: it turns model.level_head on in a trained checkpoint and fits the head on its
own training data (SGAN.calibrate), into ``--out``/<name of CKPT> (how the shipped weights got theirs).

    python -m benchmarks.pretrain --out DIR --device cuda --steps 500 --budget-s 400
"""
from __future__ import annotations

import argparse
import json
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from benchmarks.common import HELDOUT_MASK, gpu_driver, keep_weights

ROOT = Path(__file__).resolve().parents[1]
MASKS = "codesign/models/pretrained/masks"  # relative to the checkout, where the runs start
POOL = ["published", f"{MASKS}/spline_half.json", f"{MASKS}/spline_eighth.json", "defocus:20", "defocus:35",
        "defocus:55"]
RUNS = ("pool_seed0", "pool_seed1", "single")


def run_overrides(name: str, a, work: Path) -> list[str]:
    common = ["+experiment=baseline", "model=sgan_b_l1", "data.params.alpha_l_spacing=log", "preset=joint_cpu",
              "trainer=joint_cpu",
              f"trainer.steps={a.steps}", f"trainer.ema={a.ema}", f"data.batch_size={a.batch}", f"device={a.device}",
              f"threads={a.threads}", "trainer.val_every=100", "trainer.image_every=0",
              f"trainer.checkpoint_every={a.checkpoint_every}", "evaluate.laser_strengths=[0,1e6]",
              "evaluate.stages=[]",
              "evaluate.max_scenes=2", f"hydra.run.dir={work / name}"]
    common += a.set
    if a.budget_s:
        common.append(f"trainer.time_budget_s={a.budget_s}")
    if name.startswith("pool"):
        return common + [f"seed={name.removeprefix('pool_seed')}", "data.masks=[" + ",".join(a.pool) + "]",
                         f"data.mask_draws={a.draws}", f"data.mask_every={a.mask_every}"]
    return common + ["seed=0", "mask=spline", f"mask.init={HELDOUT_MASK}"]


def fit_level(src: Path, out: Path, device: str, crops: int) -> dict:
    """The checkpoint ``src`` with model.level_head on and fitted (its network unchanged), written to out/src.name."""
    from codesign.models.level import N_FEATURES
    from codesign.train.checkpoint import load_checkpoint, save_checkpoint
    from codesign.train.data import SimulatedData
    from codesign.train.resume import load_trained

    state = load_checkpoint(src)
    state["config"]["model"]["level_head"] = True
    if state.get("model_spec"):
        state["model_spec"]["level_head"] = True
    unfitted = torch.zeros(N_FEATURES, dtype=torch.float64)  # the head's weight before its fit: gain 1
    state["model"]["g2.level.weight"] = unfitted
    if state.get("ema"):
        state["ema"][2]["level.weight"] = unfitted
    out.mkdir(parents=True, exist_ok=True)
    dst, staged = out / src.name, out / (src.stem + ".staged.pt")
    save_checkpoint(staged, state)  # load_trained reads a file: the checkpoint as it will be, with an unfitted head
    try:
        model, generators, cfg, _ = load_trained(staged, torch.device(device))
    finally:
        staged.unlink()
    facts = model.calibrate(generators, SimulatedData(cfg, torch.device(device), int(cfg.seed)), crops=crops,
                            refit=True)
    state["model"] = model.state_dict()
    if state.get("ema"):
        state["ema"] = [g.state_dict() for g in generators]
    state["record"] = {**(state.get("record") or {}), **facts}
    save_checkpoint(dst, state)
    return {"source": str(src), "written": str(dst), **facts}


def device_facts(device: str) -> dict:
    facts = {"torch": torch.__version__, "python": platform.python_version(), "machine": platform.processor() or
             platform.machine(), "date": time.strftime("%Y-%m-%d")}
    if device.startswith("cuda") and torch.cuda.is_available():
        facts.update(gpu=torch.cuda.get_device_name(0), cuda=torch.version.cuda, driver=gpu_driver())
    return facts


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--device", default="cuda")
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--budget-s", type=float, default=400.0, help="each run's training time budget (null: none)")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--ema", type=float, default=0.995)
    p.add_argument("--draws", type=int, default=2, help="data.mask_draws")
    p.add_argument("--mask-every", type=int, default=4, help="data.mask_every")
    p.add_argument("--threads", type=int, default=4)
    p.add_argument("--checkpoint-every", type=int, default=100)
    p.add_argument("--runs", default=",".join(RUNS))
    p.add_argument("--pool", default=",".join(POOL), help="the pool runs' data.masks (comma-separated)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a further override of every run (repeatable), e.g. --set model.g1_halo=true")
    p.add_argument("--dry-run", action="store_true", help="a CPU rehearsal: 2 steps, batch 2, one draw")
    p.add_argument("--fit-level", type=Path, metavar="CKPT", help="fit model.level_head into this checkpoint only")
    p.add_argument("--level-crops", type=int, default=1024, help="--fit-level: training crops of the fit")
    a = p.parse_args(argv)
    if a.fit_level is not None:
        if not a.fit_level.is_file():
            p.error(f"--fit-level: no file {a.fit_level}")
        print(json.dumps(fit_level(a.fit_level, a.out, a.device, a.level_crops), indent=2))
        return 0
    if a.dry_run:
        a.device, a.steps, a.batch, a.draws, a.budget_s, a.threads = "cpu", 2, 2, 0, None, 1
    runs = [r.strip() for r in a.runs.split(",") if r.strip()]
    a.pool = [m.strip() for m in a.pool.split(",") if m.strip()]
    unknown = sorted(r for r in runs if r not in RUNS and not re.fullmatch(r"pool_seed[0-9]+", r))
    if unknown:
        p.error(f"--runs: unknown {unknown}; allowed: {', '.join(RUNS)} or pool_seed<k> (the pool with seed k)")
    a.out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="codesign_pretrain_"))
    record = {"facts": device_facts(a.device), "args": {k: str(v) for k, v in vars(a).items()}, "pool": a.pool,
              "heldout_mask": str(HELDOUT_MASK.relative_to(ROOT)), "runs": {}}
    procs, t0 = {}, time.perf_counter()
    for name in runs:
        cmd = [sys.executable, "-m", "codesign", *run_overrides(name, a, work)]
        log = open(work / f"{name}.log", "w")
        procs[name] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT), log, cmd)
        print(f"started {name}: {' '.join(cmd[1:])}", flush=True)
        if a.dry_run:  # one at a time on a small CPU
            procs[name][0].wait()
    for name, (proc, log, cmd) in procs.items():
        rc = proc.wait()
        log.close()
        run = work / name
        metrics = json.loads((run / "metrics.json").read_text()) if (run / "metrics.json").is_file() else {}
        keep = {k: v for k, v in metrics.items() if k.startswith(("psnr", "ssim", "steps", "seconds", "mask_pool",
                                                                  "loss_last", "parameters"))}
        record["runs"][name] = {"command": " ".join(["python"] + cmd[1:]).replace(str(work), "RUN"), "exit": rc,
                                "wall_s": round(time.perf_counter() - t0, 1), **keep}
        if (run / "checkpoint.pt").is_file():
            record["runs"][name].update(keep_weights(run / "checkpoint.pt", a.out / f"{name}.pt"))
        print(f"{name}: exit {rc}, steps {metrics.get('steps')}, {metrics.get('seconds', float('nan')):.0f} s",
              flush=True)
    with open(a.out / "pretrain.log", "w") as out:
        for name in runs:
            out.write(f"==== {name}\n" + (work / f"{name}.log").read_text() + "\n")
    (a.out / "pretrain.json").write_text(json.dumps(record, indent=2) + "\n")
    return 0 if all(r["exit"] == 0 for r in record["runs"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
