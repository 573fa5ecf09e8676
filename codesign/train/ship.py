"""A trained checkpoint as weights to ship: ``python -m codesign.train.ship CHECKPOINT OUT.pt``.

Keeps what restoring and a warm start need (the generators' EMA averages folded into the model's state, or the last
step's weights; the step, the configuration, a joint run's learned mask) and drops the optimizers, schedules and
random states (a quarter of the size for wiener_naf). The stored configuration's scene source becomes the built-in
one: a corpus folder is part of a checkout, not of an installation, and ``evaluate`` / ``sensor_image`` read the
checkpoint's scenes; ``record["trained_on"]`` keeps what it trained on. How
codesign/models/pretrained/wiener_naf_pool.pt was made (its README.md).
"""
from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import torch

from codesign.errors import ConfigError
from codesign.train.checkpoint import save_checkpoint


WEIGHTS = ("ema", "last")


def shipped_state(checkpoint: str | Path, weights: str = "ema") -> dict:
    """The weights-only state of a trained ``checkpoint`` (ConfigError when it is not one): its generators' EMA
    averages (``weights="ema"``, what evaluating the checkpoint restores with) or the last step's weights
    (``"last"``: for a run whose average still holds weights of a higher learning rate)."""
    from codesign.train.resume import load_trained

    if weights not in WEIGHTS:
        raise ConfigError("weights", weights, f"must be one of {', '.join(WEIGHTS)}")
    model, generators, _, state = load_trained(checkpoint, torch.device("cpu"))
    if weights == "ema":
        for module, restoring in zip(model.generators(), generators):  # a checkpoint without EMA: the same
            module.load_state_dict(restoring.state_dict())
    config = copy.deepcopy(state["config"])
    data = config["data"]
    record = dict(state.get("record") or {})
    record["trained_on"] = {"data.scenes": data.get("scenes"), "data.folder": data.get("folder")}
    record.update({"seconds": state.get("seconds"), "versions": state.get("versions"), "weights": weights})
    data["scenes"], data["folder"] = "builtin", None
    tensors = {k: v.detach().clone() for k, v in model.state_dict().items()}
    shipped = {"model": tensors, "step": int(state["step"]), "config": config, "record": record}
    if "mask" in state:  # a joint run's learned mask: evaluate and restore image through it
        shipped["mask"] = state["mask"]
    return shipped


def main(argv=None) -> int:
    """The command line: write ``out`` (never overwriting) from ``checkpoint``; exit status 0, or 2 with the reason on
    stderr when the checkpoint is not a trained one."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", type=Path, help="a checkpoint.pt written by baseline or joint")
    p.add_argument("out", type=Path, help="the weights file to write (not overwritten)")
    p.add_argument("--weights", choices=WEIGHTS, default="ema",
                   help="the generators' EMA averages (default) or the last step's weights")
    a = p.parse_args(argv)
    if a.out.exists():
        p.error(f"out: {a.out} exists: name a new file (an earlier result is never overwritten)")
    try:
        state = shipped_state(a.checkpoint, a.weights)
    except ConfigError as err:
        print(f"codesign: {err}", file=sys.stderr)
        return 2
    save_checkpoint(a.out, state)  # atomic: a crash leaves no half-written file
    print(f"{a.out}: step {state['step']}, {a.weights} weights, {a.out.stat().st_size / 2**20:.2f} MiB, trained on "
          f"{state['record']['trained_on']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
