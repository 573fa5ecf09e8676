"""Data-parallel training under torchrun: the process group, DDP wrapping and the few collectives the trainer uses.

``torchrun --nproc_per_node=N -m codesign +experiment=...`` starts N copies of the same command with RANK,
WORLD_SIZE and LOCAL_RANK in their environment. ``launch_setup`` (called by ``python -m codesign`` before Hydra
composes) joins the process group and shares rank 0's run-directory stamp, so every rank reads and resumes the
same run directory while only rank 0 writes into it. Backends: nccl for CUDA tensors, gloo for CPU tensors (both
are registered when CUDA is present, so ``device=cpu`` also works on a GPU machine).

Semantics (docs/scaling.md): ``data.batch_size`` is the global batch, split evenly across ranks; every rank draws
the random choices of the whole global batch (cheap scalars) and simulates only its own share, with noise seeded
per sample, so a run's batches do not depend on the number of processes. DDP averages the gradients, hence a
step equals the single-process step on the same global batch, and a checkpoint resumes under any world size.
"""
from __future__ import annotations

import datetime as _dt
import logging
import os
import sys
from dataclasses import dataclass

import torch
import torch.distributed as dist

from codesign.config.resolvers import STAMP_ENV, STAMP_FORMAT, env_rank

log = logging.getLogger("codesign.distributed")

TIMEOUT_MIN = 60  # a rank waits this long at a collective (rank 0 validating, evaluating) before giving up


@dataclass(frozen=True)
class DistContext:
    """Where this process stands: rank, world size, and the local rank (its GPU on a node)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        """Whether more than one process trains (under torchrun)."""
        return self.world > 1

    @property
    def is_main(self) -> bool:
        """Whether this process is rank 0 (the one that logs, evaluates and writes)."""
        return self.rank == 0

    def shard(self, n: int) -> slice:
        """This rank's contiguous share of a global batch of ``n`` (n divisible by world, checked by the data)."""
        b = n // self.world
        return slice(self.rank * b, (self.rank + 1) * b)


SINGLE = DistContext()


def env_context() -> DistContext:
    """The torchrun environment of this process (SINGLE outside torchrun)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return SINGLE
    return DistContext(env_rank(), world, int(os.environ.get("LOCAL_RANK", "0")))


def current() -> DistContext:
    """The process group's context once joined, else SINGLE (a plain run, a test calling the experiments directly)."""
    if dist.is_available() and dist.is_initialized():
        return DistContext(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", "0")))
    return SINGLE


def _backend() -> str:
    return "cpu:gloo,cuda:nccl" if torch.cuda.is_available() else "gloo"


def launch_setup(argv: list[str]) -> DistContext:
    """Under torchrun: join the process group and share rank 0's run stamp (STAMP_ENV); else nothing."""
    ctx = env_context()
    if not ctx.enabled:
        return ctx
    if any(a in ("-m", "--multirun") or a.startswith("--multirun=") for a in argv):
        # every rank says it: torchrun stops the others when the first one exits, which can be before rank 0
        # has got this far (a silent failure seen on a loaded 2-core machine)
        print("codesign: configuration error: -m/--multirun cannot run under torchrun: run the sweep with a "
              "launcher (docs/scaling.md) and torchrun inside each job, or launch one torchrun per point",
              file=sys.stderr, flush=True)
        raise SystemExit(2)
    if torch.cuda.is_available():
        torch.cuda.set_device(ctx.local_rank)
    if not dist.is_initialized():
        dist.init_process_group(_backend(), timeout=_dt.timedelta(minutes=TIMEOUT_MIN))
    stamp = [_dt.datetime.now().strftime(STAMP_FORMAT) if ctx.is_main else None]
    dist.broadcast_object_list(stamp, src=0, device=torch.device("cpu"))
    os.environ[STAMP_ENV] = stamp[0]
    return ctx


def finish() -> None:
    """Destroy the process group, when one was started."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


# ---- collectives the trainer uses --------------------------------------------------------------------------
def wrap(module: torch.nn.Module, ctx: DistContext, device: torch.device) -> torch.nn.Module:
    """``module`` under DistributedDataParallel when ``ctx`` is distributed (the same module otherwise).

    The wrapper shares the module's parameters, so checkpoints keep saving the plain module's state. No buffers
    to broadcast (the networks hold none that change), hence broadcast_buffers=False: no collective per forward.
    """
    if not ctx.enabled:
        return module
    from torch.nn.parallel import DistributedDataParallel as DDP

    ids = [device.index if device.index is not None else ctx.local_rank] if device.type == "cuda" else None
    # torch >= 2.13 names it forward_sync_buffers (broadcast_buffers is deprecated there)
    import inspect

    key = "forward_sync_buffers" if "forward_sync_buffers" in inspect.signature(DDP).parameters else \
        "broadcast_buffers"
    return DDP(module, device_ids=ids, **{key: False})


def all_mean(values: dict[str, torch.Tensor], ctx: DistContext) -> dict[str, float]:
    """Floats of the 0-dim tensors in ``values``, averaged over the ranks: the global batch's values (one
    collective; call on every rank at the same step)."""
    keys = sorted(values)
    if not keys:
        return {}
    flat = torch.stack([values[k].detach().float().reshape(()) for k in keys])
    if ctx.enabled:
        dist.all_reduce(flat)
        flat = flat / ctx.world
    return dict(zip(keys, flat.cpu().tolist()))


def any_rank(flag: torch.Tensor, ctx: DistContext) -> torch.Tensor:
    """A 0-dim bool that is true on every rank when it is true on any (stays on the device: no host sync)."""
    if not ctx.enabled:
        return flag
    f = flag.to(torch.float32)
    dist.all_reduce(f, op=dist.ReduceOp.MAX)
    return f > 0


@torch.no_grad()
def replica_divergence(params: list[torch.Tensor], ctx: DistContext, resync: bool = True) -> float:
    """Largest |p - p on rank 0| over ``params`` and ranks (0.0 when identical, as DDP keeps them). With
    ``resync`` a divergence is repaired by copying rank 0's values. One broadcast and one all-reduce."""
    if not ctx.enabled or not params:
        return 0.0
    mine = torch.cat([p.detach().reshape(-1).to(torch.float64) for p in params])
    ref = mine.clone()
    dist.broadcast(ref, src=0)
    diff = (mine - ref).abs().max().reshape(1)
    dist.all_reduce(diff, op=dist.ReduceOp.MAX)
    worst = float(diff)
    if worst > 0 and resync:
        offset = 0
        for p in params:
            n = p.numel()
            p.copy_(ref[offset:offset + n].view_as(p).to(p.dtype))
            offset += n
    return worst


def backend_name() -> str:
    """The torch.distributed backend in use (none without a process group)."""
    return dist.get_backend() if dist.is_available() and dist.is_initialized() else "none"


def broadcast_flag(flag: bool, ctx: DistContext) -> bool:
    """Rank 0's ``flag`` on every rank (e.g. its clock's verdict on the time budget)."""
    if not ctx.enabled:
        return flag
    t = torch.tensor([1.0 if flag else 0.0])  # a CPU tensor: gloo carries it (nccl is for CUDA tensors)
    dist.broadcast(t, src=0)
    return bool(t.item())


def settle(ctx: DistContext, seconds: float = 30.0) -> None:
    """Wait (at most ``seconds``) until every rank got here: before rank 0 removes a refused run's folder, which
    a slower rank's Hydra may still be creating. Never raises: a rank that does not come is not waited for."""
    if not ctx.enabled:
        return
    try:
        dist.monitored_barrier(timeout=_dt.timedelta(seconds=seconds), wait_all_ranks=True)
    except Exception as err:  # noqa: BLE001 - best effort on an error path
        log.debug("ranks did not settle: %s", err)


def barrier(ctx: DistContext) -> None:
    """Wait for every rank (nothing to wait for in one process)."""
    if ctx.enabled:
        dist.barrier()
