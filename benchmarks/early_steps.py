"""How the restoration of held-out photographs moves over the first training steps of the main job's network.

Trains the network of ``+experiment=joint``'s CPU default (model=sgan_b_gated, cpu width, 96 px padded to 128,
batch 4, EMA 0.99) with the published mask frozen, in this process, and at the chosen steps scores PSNR after the
per-image gain/offset match on the held-out photographs (default alpha_l = 0 and 1e6; --presets): the network,
G2's base (the network without G2's learned correction), its G1 output I_b^, the sensor image, classical Wiener and
Wiener after G1 (docs/models.md Sec. 10). Overrides are Hydra's, e.g. ``model=sgan_b trainer.ema=null`` (the main
job's network before 2026-11-27).

    python -m benchmarks.early_steps --steps 160 --at 0,40,160 --presets laser_0,laser_1e3,laser_1e5,laser_1e6
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import torch

from benchmarks.common import compose, write_json

SCENES = Path(__file__).resolve().parents[2] / "shared" / "data" / "scenes"
MAIN_JOB = ["+experiment=baseline", "preset=joint_cpu", "trainer=joint_cpu", "model=sgan_b_gated",
            "logging.tensorboard=false"]


PRESETS = ("laser_0", "laser_1e6")


def scores(model, trainer, data, held_out, scenes, seed: int, presets=PRESETS) -> dict:
    """PSNR matched of every method under each preset (default alpha_l = 0 and 1e6; baselines tuned for each
    condition on the training distribution)."""
    from codesign.train.evaluation import EvaluateSpec, Evaluator, centre

    ev = Evaluator(model, trainer.restoring_modules(), held_out, batch_size=EvaluateSpec.batch_size)
    ev.tune_per_condition(data.validation_scenes(8), data.validation_noise_seed)
    out = {}
    for preset in presets:
        batch, _, target, table = ev.score_preset(scenes, preset, seed + 1000 + noise_offset(preset))
        inner = inner_images(model, trainer, batch, data.otf)
        table.update(ev.score({name: centre(x, ev.n) for name, x in inner.items()}, target))
        out[preset] = {m: round(float(table[m]["psnr_matched"]), 2) for m in table}
        out[preset]["tuned_nsr"] = {k: float(f"{v:.3g}") for k, v in ev.calib["nsr"].items()}
    out["learned"] = learned_scalars(trainer)
    return out


def noise_offset(preset: str) -> int:
    """A fixed noise stream per condition, whichever others are scored (0 and 1 as before --presets existed)."""
    from codesign.data.params import PRESETS as KNOWN

    return PRESETS.index(preset) if preset in PRESETS else 2 + list(KNOWN).index(preset)


@torch.no_grad()
def inner_images(model, trainer, batch: dict, otf: torch.Tensor) -> dict:
    """The restoring generators' inner images of ``batch``: G1's output I_b^ and, with a residual G2, G2's base
    (what its learned correction is added to: the network without that correction), as "i_b" and "g2_base"."""
    outs = [model.restore(sensor, otf, trainer.restoring_modules()) for sensor in batch["sensor"].split(8)]
    return {name: torch.cat([o[key] for o in outs]) for key, name in (("i_b", "i_b"), ("base", "g2_base"))
            if key in outs[0]}


def learned_scalars(trainer) -> dict:
    """The restoring G2's learned scalars where present: base nsr (unlasered, lasered), the laser gate's f0."""
    g2 = trainer.restoring_modules()[2]
    names = {"log_nsr": "nsr", "log_nsr_lasered": "nsr_lasered", "log_f0": "f0"}
    return {label: float(f"{float(getattr(g2, name).exp()):.4g}") for name, label in names.items()
            if getattr(g2, name, None) is not None}


def main(argv=None) -> int:
    from codesign.config.runtime import to_container
    from codesign.train.data import SimulatedData
    from codesign.train.model_setup import build_model
    from codesign.train.spec import TrainerSpec
    from codesign.train.optim import init_weights
    from codesign.train.trainer import Trainer

    ap = argparse.ArgumentParser(prog="python -m benchmarks.early_steps", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=40, help="training steps (default 40)")
    ap.add_argument("--at", default="0,1,10,40", help="steps at which to score (comma-separated)")
    ap.add_argument("--scenes", type=Path, default=SCENES, help="held-out photographs (default ../shared/data/scenes)")
    ap.add_argument("--out", type=Path, default=None, help="write the scores as JSON here (after every scoring)")
    ap.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    ap.add_argument("--presets", default=",".join(PRESETS),
                    help=f"evaluation conditions, comma-separated (default {','.join(PRESETS)}; laser_0, "
                         "laser_1e1 .. laser_1e6, E1 .. H2)")
    ap.add_argument("overrides", nargs="*", help="Hydra overrides of the run")
    a = ap.parse_args(argv)
    at = sorted({int(v) for v in a.at.split(",") if v.strip()})
    if a.steps < 0 or not at or at[0] < 0 or at[-1] > a.steps:
        ap.error(f"--at {a.at!r}: steps between 0 and --steps {a.steps}")
    from codesign.data.params import PRESETS as KNOWN

    presets = tuple(v.strip() for v in a.presets.split(",") if v.strip())
    if not presets or any(v not in KNOWN for v in presets):
        ap.error(f"--presets {a.presets!r}: allowed {', '.join(KNOWN)} (comma-separated)")
    if not a.scenes.is_dir():
        ap.error(f"--scenes {a.scenes}: no such folder")
    try:
        dev = torch.device(a.device)
    except RuntimeError:
        ap.error(f"--device {a.device!r}: cpu, cuda or cuda:N")
    if dev.type == "cuda" and not torch.cuda.is_available():
        ap.error(f"--device {a.device}: no CUDA device visible (torch {torch.__version__})")
    if dev.type not in ("cpu", "cuda"):
        ap.error(f"--device {a.device!r}: cpu, cuda or cuda:N")
    cfg = compose([*MAIN_JOB, *a.overrides])
    held_cfg = compose([*MAIN_JOB, "data.scenes=folder", f"data.folder={a.scenes}", *a.overrides])
    seed = int(cfg.seed)
    torch.manual_seed(seed)
    model = build_model(cfg)
    init_weights(model)  # on the CPU: the same initial weights on every device
    model = model.to(dev)
    data = SimulatedData(cfg, dev, seed)
    held_out = SimulatedData(held_cfg, dev, seed, camera=data.camera)
    spec = TrainerSpec.from_config(to_container(cfg.trainer)).replace(steps=max(a.steps, 1), val_every=0,
                                                                      checkpoint_every=0, image_every=0)
    run_dir = Path(tempfile.mkdtemp(prefix="codesign_early_"))  # the trainer's folder: nothing is kept
    trainer = Trainer(model=model, data=data, spec=spec, run_dir=run_dir, device=dev, config=to_container(cfg),
                      seed=seed)
    names = held_out.source.split_names("all")[:12]
    scenes = held_out.source.fixed_batch(names, data.camera.scene_size)
    t0, res = time.perf_counter(), {"overrides": a.overrides, "device": str(dev), "scenes": names, "steps": {}}
    for step in range(a.steps + 1):
        if step in at:
            res["steps"][step] = scores(model, trainer, data, held_out, scenes, seed, presets)
            res["seconds"] = round(time.perf_counter() - t0, 1)
            print(f"step {step:4d} ({res['seconds']:5.0f} s): {json.dumps(res['steps'][step])}", flush=True)
            if a.out:  # after every scoring: a run cut short keeps what it measured
                write_json(a.out, res)
        if step < a.steps:
            trainer.train_step()
    return 0


if __name__ == "__main__":
    sys.exit(main())
