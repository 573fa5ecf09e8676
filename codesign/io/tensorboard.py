"""TensorBoard writers of a run directory: every experiment writes its events into its own run directory, so
``tensorboard --logdir outputs`` lists all runs side by side."""
from __future__ import annotations

import math
from pathlib import Path

from codesign.config.runtime import logging_spec


def tensorboard_enabled(cfg) -> bool:
    """``logging.tensorboard`` of a composed config (the LoggingSpec default when the block is absent)."""
    return logging_spec(cfg).tensorboard


def open_writer(run_dir: Path, enabled: bool = True, purge_step: int | None = None):
    """A SummaryWriter on ``run_dir`` (None when ``enabled`` is false)."""
    if not enabled:
        return None
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(log_dir=str(run_dir), purge_step=purge_step or None)


def log_summary(writer, hparams: dict, metrics: dict, prefix: str = "final") -> None:
    """Every scalar of a run's metrics.json as ``prefix/<key>`` at step 0, plus the hparams table; closes the
    writer. Non-scalar entries (tables, lists) stay in metrics.json."""
    if writer is None:
        return
    scalars = {k: float(v) for k, v in metrics.items()
               if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))}
    for k, v in scalars.items():
        writer.add_scalar(f"{prefix}/{k}", v, 0)
    hp = {k: (v if isinstance(v, (int, float, str, bool)) else str(v)) for k, v in hparams.items()}
    writer.add_hparams(hp, {f"hparam/{k}": v for k, v in scalars.items()}, run_name="hparams")
    writer.close()
