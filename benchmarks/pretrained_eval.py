"""``python -m benchmarks.pretrained_eval``: a restorer checkpoint against classical Wiener and the sensor image, mask
by mask, on photographs it never trained on (issue 35's quality goal and its "one restorer for any mask" control).

For every mask it runs ``+experiment=evaluate checkpoint=CKPT mask=...`` on the scenes folder (default: the 12
photographs of ../shared/data/scenes, all of them) at alpha_l = 0, 1e3, 1e5, 1e6, and reports per mask and laser
strength: PSNR after the gain/offset match, plain PSNR and SSIM of the network, of Wiener (tuned per condition) and
of the sensor image, and the network's paired gain over each (mean over the scenes +- the 95 % interval of the
per-scene differences).

    python -m benchmarks.pretrained_eval --checkpoint pretrained --masks published,heldout \\
        --out benchmarks/results/pretrained/eval_pool_seed0.json

Masks: ``published`` (the five half rings), ``heldout`` (benchmarks/results/pretrained/heldout_mask.json.gz, the spline
design at a quarter of the published peak that no pool held), or the path of any mask record.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import mask_overrides
from codesign.train.evaluation import BASELINES
from codesign.train.summary import paired_difference

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT.parent / "shared" / "data" / "scenes"
ALPHAS = ("0", "1e3", "1e5", "1e6")
FLOORS = ("wiener", "sensor")


def evaluate(checkpoint: str, mask: str, scenes: Path | str, threads: int, work: Path,
             size: tuple[int, int] | None = None) -> dict:
    """``+experiment=evaluate`` of ``checkpoint`` through ``mask`` on the photographs of ``scenes`` (a folder, or
    'heldout': the package's 16); ``size``: (data.image_size, data.padded_size) to evaluate at, for a network that
    takes any size (None: the checkpoint's)."""
    run = work / f"{mask.replace('/', '_')}_{size[0] if size else 'own'}_{Path(str(scenes)).name}"
    source = ["evaluate.scenes=heldout"] if str(scenes) == "heldout" else [
        "data.scenes=folder", f"data.folder={scenes}", "evaluate.scenes=data", "evaluate.split=all"]
    sizes = [f"data.image_size={size[0]}", f"data.padded_size={size[1]}"] if size else []
    cmd = [sys.executable, "-m", "codesign", "+experiment=evaluate", f"checkpoint={checkpoint}",
           *mask_overrides(mask), *source, *sizes, "evaluate.max_scenes=100",
           f"evaluate.laser_strengths=[{','.join(ALPHAS)}]",
           "evaluate.stages=[]", f"threads={threads}", "logging.tensorboard=false", f"hydra.run.dir={run}"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"evaluate failed on mask {mask}:\n{proc.stderr[-3000:]}")
    m = json.loads((run / "metrics.json").read_text())
    out = {"command": "python " + " ".join(cmd[1:-1]), "seconds": round(time.perf_counter() - t0, 1),
           "scenes": m["evaluation_scenes"], "steps": m.get("steps"), "alpha": {}}
    for a in ALPHAS:
        cond = f"laser_{a}"
        table, per = m["evaluation"][cond], m["evaluation_per_scene_psnr_matched"][cond]
        # the restorer's column: its method name (sgan, wiener_unet), the one that is no baseline; stored as "sgan"
        net = next(k for k in table if k not in BASELINES)
        row = {meth: {q: round(table[src][q], 3) for q in ("psnr_matched", "psnr", "ssim")}
               for meth, src in (("sgan", net), *((f, f) for f in FLOORS))}
        for floor in FLOORS:
            mean, half = paired_difference(per[net], per[floor])
            row[f"gain_over_{floor}"] = {"mean": round(mean, 3), "interval": None if half is None else round(half, 3)}
        out["alpha"][a] = row
    return out


def table(result: dict) -> str:
    lines = []
    for mask, r in result["masks"].items():
        lines.append(f"mask {mask} ({len(r['scenes'])} scenes; checkpoint step {r['steps']}): PSNR matched / plain "
                     f"/ SSIM, and the network's gain over Wiener and over the sensor image (matched PSNR, 95 %)")
        for a, row in r["alpha"].items():
            cells = "  ".join(f"{m} {row[m]['psnr_matched']:.2f}/{row[m]['psnr']:.2f}/{row[m]['ssim']:.3f}"
                              for m in ("sgan", *FLOORS))
            gw, gs = row["gain_over_wiener"], row["gain_over_sensor"]
            lines.append(f"  alpha_l={a:>4}: {cells}  | vs wiener {gw['mean']:+.2f} +- {gw['interval']:.2f}  "
                         f"vs sensor {gs['mean']:+.2f} +- {gs['interval']:.2f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True, help="a checkpoint path or 'pretrained'")
    p.add_argument("--masks", default="published,heldout")
    p.add_argument("--scenes", default=str(SCENES), help="a folder of photographs, or 'heldout' (the package's)")
    p.add_argument("--size", type=int, nargs=2, metavar=("IMAGE", "PADDED"),
                   help="data.image_size and data.padded_size to evaluate at (a network that takes any size)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", type=Path, required=True)
    a = p.parse_args(argv)
    if a.scenes != "heldout" and not Path(a.scenes).is_dir():
        p.error(f"--scenes: neither 'heldout' nor a folder: {a.scenes}")
    scenes = a.scenes if a.scenes == "heldout" else Path(a.scenes).resolve()
    work = Path(tempfile.mkdtemp(prefix="codesign_pretrained_eval_"))
    result = {"checkpoint": a.checkpoint, "scenes_folder": str(scenes), "date": time.strftime("%Y-%m-%d"),
              "size": a.size, "masks": {}}
    for mask in [m.strip() for m in a.masks.split(",") if m.strip()]:
        result["masks"][mask] = evaluate(a.checkpoint, mask, scenes, a.threads, work, tuple(a.size) if a.size else None)
        print(table({"masks": {mask: result["masks"][mask]}}), flush=True)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = a.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=2) + "\n")
    tmp.replace(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
