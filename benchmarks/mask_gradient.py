"""The mask gradient's signal against its batch-to-batch noise, at the main job's setting.

    python -m benchmarks.mask_gradient --checkpoint PATH [--batches 24] [--seed 0] [--out FILE] [OVERRIDE ...]

The joint configuration (``+experiment=joint`` and any OVERRIDE: the published half-ring mask, trainable) with a
restorer trained on that mask (``--checkpoint``, e.g. a main-job run's published/checkpoint.pt, whose generators'
EMA averages are what it restores with). For each of ``--batches`` training batches (the trainer's draws of steps
0, 1, ...), the gradient of the restorer's generator objective (for the SGAN: Charbonnier, adversarial and MDF terms
at the config's weights) with respect to the mask's parameters, one batch at a time. The mask's LSR term is left
out: it does not depend on the batch.

Reported, over the batches: the mean gradient's norm (its sample estimate less the noise that estimate carries),
the root-mean-square distance of one batch's gradient from the mean, their ratio (the signal-to-noise ratio of one
batch's gradient; the mean of n batches has sqrt(n) times it), the mean pairwise cosine between batch gradients, the
batches that an SNR of 1 and of 3 need, and per parameter mean / standard deviation (Adam divides each parameter's
step by its gradient's RMS, so a parameter whose per-batch SNR is below 1 moves mostly at random).
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch


def gradients(cfg, checkpoint: Path, batches: int, seed: int) -> tuple[torch.Tensor, list[str]]:
    """(batches, parameters) mask gradients of the generator objective, one row per training batch."""
    from codesign.models.restorer import TrainContext
    from codesign.train.data import SimulatedData
    from codesign.train.model_setup import build_model
    from codesign.train.resume import load_initial_weights

    torch.manual_seed(seed)
    model = build_model(cfg)
    load_initial_weights(model, checkpoint, cfg, "--checkpoint")
    model.prepare_training(torch.device("cpu"))
    data = SimulatedData(cfg, torch.device("cpu"), seed)
    data.camera.set_trainable(True)
    named = [(n, p) for n, p in data.camera.mask.named_parameters() if p.requires_grad]
    names = [f"{n}[{i}]" for n, p in named for i in range(p.numel())]
    ctx = TrainContext(model.critics())
    for m in model.generators() + model.critics():
        m.train()
    rows = []
    for step in range(batches):
        batch = data.train_batch(step)
        out = model.forward_with(model.generators(), batch["sensor"], batch["otf"])
        total = model.generator_losses(batch, out, ctx)["generator_total"]
        grads = torch.autograd.grad(total, [p for _, p in named])
        rows.append(torch.cat([g.reshape(-1) for g in grads]).double())
        print(f"  batch {step + 1}/{batches}: |g| = {float(rows[-1].norm()):.4g}", flush=True)
    return torch.stack(rows), names


def statistics(g: torch.Tensor, names: list[str]) -> dict:
    n = g.shape[0]
    mean = g.mean(0)
    # one batch's noise: the RMS distance of a batch's gradient from the true mean (unbiased, n - 1); the signal:
    # the true mean's norm, |sample mean|^2 less the noise the sample mean still carries (noise^2 / n)
    noise = float(((g - mean).pow(2).sum(1).sum() / (n - 1)).sqrt())
    signal = math.sqrt(max(float(mean.norm()) ** 2 - noise ** 2 / n, 0.0))
    snr = signal / noise
    unit = g / g.norm(dim=1, keepdim=True)
    cos = unit @ unit.T
    pairwise = float((cos.sum() - cos.diagonal().sum()) / (n * (n - 1)))
    std = g.std(0)
    never = snr == 0
    return {"batches": n, "sample_mean_norm": float(mean.norm()), "mean_gradient_norm": signal,
            "batch_noise_rms": noise, "snr_one_batch": snr, "mean_pairwise_cosine": pairwise,
            "batches_for_snr_1": None if never else math.ceil(1 / snr ** 2 - 1e-9),  # not 7 for 6.000000000001
            "batches_for_snr_3": None if never else math.ceil(9 / snr ** 2 - 1e-9),
            "per_parameter": {k: {"mean": float(m), "std": float(s), "snr": float(abs(m) / s)}
                              for k, m, s in zip(names, mean, std)}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.mask_gradient", description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", type=Path, required=True, help="a restorer trained on the joint config's mask")
    ap.add_argument("--batches", type=int, default=24)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, help="write the figures as JSON here")
    ap.add_argument("overrides", nargs="*", help="Hydra overrides on +experiment=joint")
    a = ap.parse_args(argv)
    if a.batches < 2:
        ap.error(f"--batches {a.batches}: at least 2 (the noise needs two batches)")
    import codesign
    from codesign.config.runtime import to_container

    cfg = codesign.compose(*a.overrides, experiment="joint")
    t0 = time.perf_counter()
    g, names = gradients(cfg, a.checkpoint, a.batches, a.seed)
    res = {"command": "python -m benchmarks.mask_gradient " + " ".join(argv if argv is not None else sys.argv[1:]),
           "date": time.strftime("%Y-%m-%d"), "threads": torch.get_num_threads(), "torch": torch.__version__,
           "seconds": time.perf_counter() - t0, "mask": to_container(cfg.mask)["kind"],
           "loss": dict(to_container(cfg.model).get("loss") or {}), **statistics(g, names)}
    print(f"mask gradient over {res['batches']} batches: |mean| {res['mean_gradient_norm']:.4g}, one batch's "
          f"noise {res['batch_noise_rms']:.4g}, SNR of one batch {res['snr_one_batch']:.3f} (batches for SNR 1: "
          f"{res['batches_for_snr_1']}, for SNR 3: {res['batches_for_snr_3']}); mean pairwise cosine "
          f"{res['mean_pairwise_cosine']:.3f}")
    for k, v in res["per_parameter"].items():
        print(f"  {k:<12} mean {v['mean']:+.4g}  std {v['std']:.4g}  SNR {v['snr']:.3f}")
    if a.out:
        from codesign.io.files import write_json

        write_json(a.out, res)
        print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
