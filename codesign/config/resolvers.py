"""OmegaConf resolvers of conf/config.yaml (registered on ``import codesign``; no torch import here).

Under torchrun every rank composes the same config; these make the ranks agree on one run directory and keep
the files Hydra itself writes (.hydra/, the job log) to rank 0, with a log file per other rank.
"""
from __future__ import annotations

import datetime as _dt
import os

from omegaconf import OmegaConf

STAMP_ENV = "CODESIGN_RUN_STAMP"  # rank 0's run-directory stamp, shared with the other ranks (distributed.py)
STAMP_FORMAT = "%Y-%m-%d_%H-%M-%S_%f"


def env_rank() -> int:
    """This process's rank under torchrun (0 outside it)."""
    return int(os.environ.get("RANK", "0")) if int(os.environ.get("WORLD_SIZE", "1")) > 1 else 0


def run_stamp(fmt: str = STAMP_FORMAT) -> str:
    """``codesign_stamp``: rank 0's stamp under torchrun, the current time otherwise (microseconds: runs started
    together never share a folder)."""
    return os.environ.get(STAMP_ENV) or _dt.datetime.now().strftime(fmt)


def rank_suffix() -> str:
    """``codesign_rank_suffix``: '' on rank 0, '.rank<k>' elsewhere (per-rank log files)."""
    r = env_rank()
    return "" if r == 0 else f".rank{r}"


def main_only(value):
    """``codesign_main_only``: ``value`` on rank 0, None on the other ranks (so they write no .hydra/)."""
    return value if env_rank() == 0 else None


def register() -> None:
    """Register this module's OmegaConf resolvers (codesign_stamp, codesign_rank_suffix, codesign_main_only) once."""
    for name, fn in (("codesign_stamp", run_stamp), ("codesign_rank_suffix", rank_suffix),
                     ("codesign_main_only", main_only)):
        if not OmegaConf.has_resolver(name):
            OmegaConf.register_new_resolver(name, fn, use_cache=True)
