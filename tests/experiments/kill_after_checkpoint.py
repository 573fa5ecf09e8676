"""``python tests/experiments/kill_after_checkpoint.py N ARGS...``: run ``python -m codesign ARGS`` and SIGKILL the
process right after its trainers' N-th checkpoint, a kill at a known step (a real SIGKILL: nothing after it runs)."""
from __future__ import annotations

import os
import runpy
import signal
import sys

from codesign.train.trainer import Trainer

KILL_AFTER = int(sys.argv[1])
_save = Trainer.save
_saves = [0]


def _save_then_kill(self, path=None):
    out = _save(self, path)
    _saves[0] += 1
    if _saves[0] == KILL_AFTER:
        os.kill(os.getpid(), signal.SIGKILL)
    return out


Trainer.save = _save_then_kill
sys.argv = ["codesign", *sys.argv[2:]]
runpy.run_module("codesign", run_name="__main__", alter_sys=True)
