"""A few co-design steps under torchrun (or in one process), each rank's final state saved for the tests.

    torchrun --nproc_per_node=2 --standalone tests/train/ddp_worker.py OUT STEPS   (ranks 0 and 1)
    python tests/train/ddp_worker.py OUT STEPS                                      (one process)

Writes OUT/rank<k>.pt (or OUT/single.pt): every parameter of the networks and the mask after STEPS joint steps,
the per-step loss terms averaged over the ranks (the global batch's), and the world size. The mask trains from
the first step (no warm-up), so its gradient goes through the DDP all-reduce at every step.
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from codesign.train import distributed  # noqa: E402
from tests.train._util import joint_trainer  # noqa: E402


def main(out: Path, steps: int) -> None:
    torch.set_num_threads(1)
    ctx = distributed.launch_setup([])
    tr = joint_trainer(out, "data.batch_size=4", dist=ctx)
    losses = []
    for _ in range(steps):
        terms = tr.train_step()
        losses.append(distributed.all_mean(terms, ctx))
    params = {f"{i}": p.detach().clone() for i, p in enumerate(tr.replicated_parameters())}
    name = f"rank{ctx.rank}.pt" if ctx.enabled else "single.pt"
    torch.save({"params": params, "losses": losses, "world": ctx.world, "mask": tr.codesign.mask.summary(),
                "divergence": distributed.replica_divergence(tr.replicated_parameters(), ctx, resync=False)},
               out / name)
    distributed.finish()


if __name__ == "__main__":
    main(Path(sys.argv[1]), int(sys.argv[2]))
