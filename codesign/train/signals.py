"""Stopping a training cleanly: SIGINT (Ctrl-C) and SIGTERM (what SLURM sends before a time limit) are read at the
next step boundary, where the trainer writes a checkpoint and raises TrainingInterrupted."""
from __future__ import annotations

import logging
import signal
import threading
from contextlib import contextmanager
from pathlib import Path

log = logging.getLogger("codesign.train")


class TrainingInterrupted(Exception):
    """SIGINT or SIGTERM arrived during training: the step in progress finished, a checkpoint was written (rank 0)
    and training stopped. ``exit_code``: 128 + the signal's number (130 for SIGINT, 143 for SIGTERM)."""

    def __init__(self, signum: int, step: int, checkpoint: Path | None):
        self.signum, self.step, self.checkpoint = signum, step, checkpoint
        self.exit_code = 128 + signum
        super().__init__(f"{signal.Signals(signum).name} at step {step}")


@contextmanager
def stop_requests():
    """SIGINT and SIGTERM append their number to the yielded list instead of stopping the process: the training
    loop reads it at the next step boundary. A second signal stops at once, as before. Outside the main thread
    (signals cannot be caught there) the list stays empty."""
    got: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield got
        return
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

    def request(signum, frame):
        if got:  # asked twice: stop now
            signal.signal(signum, old[signum] if callable(old[signum]) else signal.SIG_DFL)
            raise KeyboardInterrupt
        got.append(signum)
        log.warning("%s: stopping after this step (checkpoint, then exit; again to stop at once)",
                    signal.Signals(signum).name)

    for s in old:
        signal.signal(s, request)
    try:
        yield got
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)
