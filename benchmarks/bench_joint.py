"""Joint step: the seconds of one co-design training step split into its parts, against the frozen-mask step.

A co-design trainer of ``+experiment=joint`` (the CPU default: the cpu-width SGAN-B, 96 px images padded to 128,
batch 4, default optics) with the mask trainable from the first step runs its own ``train_step``; clocks around the
public methods that step calls split it into: mask -> phase -> PSF, PSF -> pixel kernel + OTF, sensor simulation
(with gradient), generator forward, critic update (D1 + both D2 scales, gradient penalty), generator losses
(critics' forward for adversarial + MDF, LSR penalty), and backward through network and optics + Adam + mask
projection + LSR guard. The same trainer then runs the step with the mask frozen (the published baseline's step:
cached optics, no mask gradient). Median of the timed steps after warm-up steps; on a GPU every clock read waits
for the device. Full scale on a GPU adds the paper's sizes (``preset=paper``).

    python -m benchmarks --only joint [--scale full]
"""
from __future__ import annotations

import statistics
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import torch
from omegaconf import OmegaConf

from benchmarks.common import Report, cuda_sync, device, finish, joint_trainer, markdown_table

PLAN = {"quick": dict(warmup=1, repeats=3), "full": dict(warmup=2, repeats=5)}
PARTS = [  # (key, what the table calls it)
    ("mask_to_psf", "mask -> phase -> PSF"),
    ("psf_to_kernel_otf", "PSF -> pixel kernel + OTF"),
    ("simulation", "sensor simulation (with gradient while the mask trains)"),
    ("generator_forward", "generator forward"),
    ("critic_update", "critic update(s) (critics' losses, gradient penalty, backward, Adam)"),
    ("generator_losses", "generator losses (critics' forward for adversarial + MDF, LSR penalty)"),
    ("backward_step_guard", "backward through network and optics, Adam, projection, LSR guard"),
    ("other", "rest of the step (schedulers, bookkeeping)"),
]


class StepClock:
    """Wall-clock intervals of named method calls during a step: ``watch(obj, name)`` shadows ``obj.name`` by an
    instance attribute that records (start, end) of each call (after a device sync) and calls the original."""

    def __init__(self, sync=None):
        self.sync = sync
        self.calls: dict[str, list[tuple[float, float]]] = {}
        self._undo: list[tuple[object, str]] = []

    def now(self) -> float:
        if self.sync:
            self.sync()
        return time.perf_counter()

    def watch(self, obj, name: str, label: str) -> None:
        fn = getattr(obj, name)

        def timed(*args, **kwargs):
            t0 = self.now()
            try:
                return fn(*args, **kwargs)
            finally:
                self.calls.setdefault(label, []).append((t0, self.now()))

        setattr(obj, name, timed)
        self._undo.append((obj, name))

    def restore(self) -> None:
        for obj, name in reversed(self._undo):
            delattr(obj, name)
        self._undo = []

    def total(self, label: str) -> float:
        return sum(b - a for a, b in self.calls.get(label, []))


@contextmanager
def watched(trainer, sync):
    """A StepClock on the methods a co-design step calls (instance attributes, removed afterwards)."""
    clock = StepClock(sync)
    camera = trainer.codesign.camera
    for obj, name, label in ((trainer.data, "train_batch", "batch"),
                             (camera, "current_optics", "optics"), (camera.simulator, "kernel", "kernel"),
                             (trainer.update, "generate", "generate"), (trainer.update, "critic_update", "critic"),
                             (trainer.update, "generator_losses", "losses"),
                             (trainer.update, "generator_update", "generator")):
        clock.watch(obj, name, label)
    try:
        yield clock
    finally:
        clock.restore()


def parts(clock: StepClock, total: float) -> dict:
    """Seconds per part of the one step (``total`` seconds) that ``clock`` watched (see PARTS)."""
    c = clock.calls
    out = {"total": total}
    if "optics" in c:  # the mask trains: its optics are recomputed with their graph inside train_batch
        (o0, o1), k0 = c["optics"][0], c["kernel"][0][0]
        out.update(mask_to_psf=k0 - o0, psf_to_kernel_otf=o1 - k0)
    out["simulation"] = clock.total("batch") - clock.total("optics")
    out["generator_forward"] = clock.total("generate")
    out["critic_update"] = clock.total("critic")
    out["generator_losses"] = clock.total("losses")
    out["backward_step_guard"] = clock.total("generator") - clock.total("losses")
    out["other"] = out["total"] - sum(v for k, v in out.items() if k != "total")
    return out


def timed_steps(trainer, step_fn, warmup: int, repeats: int, sync) -> dict:
    """Median seconds per part over ``repeats`` steps of ``step_fn`` after ``warmup`` steps."""
    for _ in range(warmup):
        step_fn()
    runs = []
    for _ in range(repeats):
        with watched(trainer, sync) as clock:
            t0 = clock.now()
            step_fn()
            total = clock.now() - t0
        runs.append(parts(clock, total))
    return {k: statistics.median(r[k] for r in runs) for k in runs[0]}


def measure_preset(overrides: list[str], dev: torch.device, warmup: int, repeats: int) -> dict:
    sync = cuda_sync(dev)
    with tempfile.TemporaryDirectory() as tmp:
        tr = joint_trainer(overrides, dev, Path(tmp))
        joint = timed_steps(tr, tr.train_step, warmup, repeats, sync)
        if "mask_to_psf" not in joint:
            raise RuntimeError("the mask did not train in the timed steps (no optics were recomputed)")

        def frozen_step():  # the restoration step with the mask frozen: the published baseline's step
            codesign, tr.codesign = tr.codesign, None
            codesign.camera.set_trainable(False)
            try:
                return tr.train_step()
            finally:
                tr.codesign = codesign

        frozen = timed_steps(tr, frozen_step, warmup, repeats, sync)
        cfg, data = OmegaConf.create(tr.config), tr.data
        info = {"model": tr.model.summary().get("variant", tr.model.kind), "model_size": str(cfg.model.size),
                "image_size": data.image_size, "padded_size": data.padded_size,
                "batch_size": int(cfg.data.batch_size), "pupil_n": tr.codesign.camera.system.grid.n,
                "focal_n": tr.codesign.camera.system.spec.focal_n, "critic_steps": tr.spec.critic_steps}
    print(f"  {' '.join(overrides) or 'joint_cpu preset'}: joint step {joint['total']:.3f} s, frozen-mask step "
          f"{frozen['total']:.3f} s", flush=True)
    return {"overrides": overrides, **info, "joint": joint, "frozen": frozen}


def measure(scale: str) -> dict:
    dev = device()
    presets = [[]] + ([["preset=paper"]] if scale == "full" and dev.type == "cuda" else [])
    p = PLAN[scale]
    return {"device": str(dev), "warmup": p["warmup"], "repeats": p["repeats"],
            "presets": [measure_preset(o, dev, p["warmup"], p["repeats"]) for o in presets]}


def report(data: dict) -> Report:
    tables, notes = [], []
    for r in data["presets"]:
        j, f = r["joint"], r["frozen"]
        rows = [[name, j.get(key, "-"), f.get(key, "-")] for key, name in PARTS]
        rows.append(["**step**", j["total"], f["total"]])
        tables.append(markdown_table(["part", "joint step [s]", "frozen-mask step [s]"], rows,
                                     {"joint step [s]": ".3f", "frozen-mask step [s]": ".3f"}))
        optics = j["mask_to_psf"] + j["psf_to_kernel_otf"] + j["simulation"]
        notes.append(
            f"`+experiment=joint{''.join(' ' + o for o in r['overrides'])}`: {r['model_size']}-width {r['model']}, "
            f"{r['image_size']} px images padded to {r['padded_size']}, batch {r['batch_size']}, pupil grid "
            f"{r['pupil_n']}^2, {r['focal_n']}^2 window, {r['critic_steps']} critic step(s) per generator step; "
            f"median of {data['repeats']} steps after {data['warmup']} warm-up step(s) on {data['device']}. The "
            f"optics (mask -> PSF -> kernel -> simulation) cost {optics:.3f} s, {optics / j['total']:.0%} of the "
            f"joint step; the joint step takes {j['total'] / f['total']:.2f}x the frozen-mask step.")
    return Report("joint", "Joint step: where the time of a co-design step goes", tables, [], notes)


def run(scale: str, out: Path) -> Report:
    data = measure(scale)
    return finish(report(data), out, scale, data)


if __name__ == "__main__":
    from benchmarks.__main__ import standalone

    standalone(run)
