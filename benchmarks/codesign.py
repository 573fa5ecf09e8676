"""Co-design benchmarks: seconds per joint training step split into its parts, and the joint-vs-published table.

    python -m benchmarks.codesign step [--preset cpu|paper] [--repeats 5]
    python -m benchmarks.codesign table RUN_DIR [RUN_DIR ...] [--tag NAME]

step: one joint step = mask -> PSF (phase + propagation), PSF -> kernel + OTF, sensor simulation (with gradient),
generator forward, critic update (D1 + both D2 scales, gradient penalty), generator losses (critics' forward for
adversarial + MDF), backward through network and optics + Adam + projection + LSR guard; plus a frozen-mask step
(the published baseline's) for comparison -> results/codesign_step_<preset>.json.
table: PSNR / SSIM (raw and affine-matched) of joint runs' learned mask vs published mask per alpha_l, with LSR and
MTF -> results/codesign_table<_tag>.json and a markdown table on stdout.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from benchmarks.common import machine, write_result


def _setup(preset: str):
    from hydra import compose, initialize_config_dir

    from codesign.train.data import JointData
    from codesign.train.joint_trainer import JointTrainer
    from codesign.design.lsr_constraint import CodesignSpec
    from codesign.tasks.baseline import _container, build_model, loss_weights
    from codesign.train.spec import TrainerSpec
    from codesign.train.trainer import init_weights

    conf = Path(__file__).resolve().parent.parent / "conf"
    overrides = ["+experiment=joint"] + (["trainer=paper"] if preset == "paper" else [])
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    torch.manual_seed(0)
    model = build_model(cfg)
    init_weights(model)
    data = JointData(cfg, dev, 0)
    spec = TrainerSpec.from_config(_container(cfg.trainer)).replace(val_every=0, checkpoint_every=0, image_every=0)
    cs = CodesignSpec.from_config({**_container(cfg.codesign), "warmup_fraction": 0.0})
    trainer = JointTrainer(model, data, spec, loss_weights(cfg), Path("/tmp"), dev, {}, None, 0, cs, 1.0)
    return cfg, trainer, dev


def _sync(dev) -> float:
    if dev.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter()


def timed_step(trainer, dev) -> dict:
    """One joint step with a clock between its parts (the same operations as JointTrainer.train_step)."""
    from codesign.models import pyramid
    from codesign.models.wiener import otf_from_kernel
    from codesign.sensor.simulator import psf_state

    data = trainer.data
    data.set_mask_trainable(True)
    trainer._before = [p.detach().clone() for p in trainer.mask.parameters()]
    t0 = _sync(dev)
    state = psf_state(data.system, data.mask.phase())
    t1 = _sync(dev)
    otf = otf_from_kernel(data.sim.kernel(state), data.padded_size).to(dev)
    t2 = _sync(dev)
    scenes = data.sampler.sample()
    params = data._params(scenes.shape[0], data.param_gen).to(dev, torch.float32)
    batch = data.sim(scenes.to(dev), params, state, seed=trainer.step, mask_key=None)
    batch["irradiance"] = batch["irradiance"].detach()
    batch.update(otf=otf, psf=state.psf, targets=pyramid(batch["scene"]))
    t3 = _sync(dev)
    out = trainer.model(batch["sensor"], otf)
    t4 = _sync(dev)
    trainer.critic_step(batch, out)
    t5 = _sync(dev)
    crits = trainer.model.discriminators()
    from codesign.train.trainer import set_requires_grad

    set_requires_grad(crits, False)
    terms = trainer.generator_losses(batch, out)
    set_requires_grad(crits, True)
    t6 = _sync(dev)
    trainer._apply(trainer.opt_g, terms["generator_total"], trainer.model.generators())
    t7 = _sync(dev)
    trainer.step += 1
    return {"mask_to_psf": t1 - t0, "psf_to_kernel_otf": t2 - t1, "simulation": t3 - t2, "generator_forward": t4 - t3,
            "critic_update": t5 - t4, "generator_losses": t6 - t5, "backward_step_guard": t7 - t6, "total": t7 - t0}


def step(preset: str, repeats: int) -> dict:
    from codesign.train.trainer import RestorationTrainer

    cfg, trainer, dev = _setup(preset)
    timed_step(trainer, dev)  # warm-up
    runs = [timed_step(trainer, dev) for _ in range(repeats)]
    parts = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    trainer.data.set_mask_trainable(False)
    frozen = []
    for _ in range(repeats + 1):
        t0 = _sync(dev)
        RestorationTrainer.train_step(trainer)
        frozen.append(_sync(dev) - t0)
    parts["frozen_mask_step"] = statistics.median(frozen[1:])
    for k, v in parts.items():
        print(f"{k:22s} {v:8.3f} s")
    return {"machine": machine(), "device": str(dev), "preset": preset, "repeats": repeats,
            "model_size": str(cfg.model.size), "image_size": int(cfg.data.image_size),
            "padded_size": int(cfg.data.padded_size), "batch_size": int(cfg.data.batch_size),
            "pupil_n": trainer.data.system.grid.n, "focal_n": trainer.data.system.spec.focal_n,
            "seconds": parts}


def table(run_dirs: list[str]) -> dict:
    rows = []
    for d in run_dirs:
        m = json.loads((Path(d) / "metrics.json").read_text())
        for cond in m["evaluation"]:
            for which, suffix in (("learned", ""), ("published", "_baseline")):
                rows.append({"run": str(d), "mask": which, "condition": cond, "steps": m["steps"],
                             "lsr": m[f"lsr{suffix}"], "lsr_smooth": m[f"lsr_smooth{suffix}"],
                             "mtf_mean": m[f"mtf_mean{suffix}"],
                             **{k: m[f"{k}{suffix}_{cond}"] for k in ("psnr", "ssim", "psnr_affine", "ssim_affine")}})
    print("| run | mask | condition | LSR | mtf_mean | PSNR | SSIM | PSNR affine | SSIM affine |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {Path(r['run']).name} | {r['mask']} | {r['condition']} | {r['lsr']:.4g} | {r['mtf_mean']:.4g} | "
              f"{r['psnr']:.2f} | {r['ssim']:.3f} | {r['psnr_affine']:.2f} | {r['ssim_affine']:.3f} |")
    return {"machine": machine(), "rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("step")
    s.add_argument("--preset", choices=("cpu", "paper"), default="cpu")
    s.add_argument("--repeats", type=int, default=5)
    t = sub.add_parser("table")
    t.add_argument("runs", nargs="+")
    t.add_argument("--tag", default="")
    args = ap.parse_args()
    if args.cmd == "step":
        path = write_result(f"codesign_step_{args.preset}", step(args.preset, args.repeats))
    else:
        path = write_result("codesign_table" + (f"_{args.tag}" if args.tag else ""), table(args.runs))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
