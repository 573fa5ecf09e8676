"""Stopping any experiment cleanly on SIGINT (Ctrl-C) or SIGTERM (what SLURM sends before a time limit).

Two modes, nested:
  interruptible()   the whole run (codesign/experiments/__init__.py): a signal raises Interrupted where the run is;
                    every output file is written atomically (codesign/io/files.py), so what was finished stays and
                    nothing is half-written; run_experiment prints one line and exits with 128 + the signal.
  stop_requests()   a region that must not be cut anywhere: a signal is only recorded (the yielded list) and the
                    region reads it where it can stop cleanly: the trainer at the next step boundary (checkpoint,
                    then TrainingInterrupted), the mask search at the next evaluation (nlopt would otherwise turn an
                    exception raised inside its objective into its own failure). A second signal stops at once.
"""
from __future__ import annotations

import logging
import signal
import threading
from contextlib import contextmanager
from pathlib import Path

log = logging.getLogger("codesign.train")

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(BaseException):
    """SIGINT or SIGTERM stopped the run. ``exit_code``: 128 + the signal's number (130 for SIGINT, 143 for
    SIGTERM); str(): the one line the user reads after "codesign: ". A BaseException, as KeyboardInterrupt: an
    ``except Exception`` on the way (a library's error handling, a cleanup) must not swallow it."""

    def __init__(self, signum: int, detail: str = ""):
        self.signum = int(signum)
        self.exit_code = 128 + self.signum
        self.detail = detail
        super().__init__(f"{self.name}{': ' + detail if detail else ''}")

    @property
    def name(self) -> str:
        """The signal's name (SIGINT, SIGTERM)."""
        return signal.Signals(self.signum).name


class TrainingInterrupted(Interrupted):
    """A signal arrived during training: the step in progress finished, a checkpoint was written (rank 0) and
    training stopped."""

    def __init__(self, signum: int, step: int, checkpoint: Path | None):
        self.step, self.checkpoint = step, checkpoint
        super().__init__(signum)
        self.args = (f"{self.name} at step {step}",)


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextmanager
def _handling(handler):
    """``handler`` on SIGINT and SIGTERM within, the previous handlers back after."""
    old = {s: signal.getsignal(s) for s in SIGNALS}
    for s in SIGNALS:
        signal.signal(s, handler)
    try:
        yield
    finally:
        for s, previous in old.items():
            signal.signal(s, previous)


@contextmanager
def interruptible():
    """Within, SIGINT and SIGTERM raise Interrupted wherever the run is (SIGTERM used to end the process without a
    word, SIGINT with a traceback). Outside the main thread (signals cannot be caught there) nothing changes."""
    if not _main_thread():
        yield
        return

    def stop(signum, frame):
        raise Interrupted(signum)

    with _handling(stop):
        yield


@contextmanager
def stop_requests(what: str = "stopping after this step (checkpoint, then exit; again to stop at once)",
                  into: list | None = None):
    """Within, SIGINT and SIGTERM append their number to the yielded list (``into`` when given: callbacks made
    before can hold it) instead of stopping the process, logging ``what`` will happen: the region reads the list
    where it can stop cleanly. A second signal raises Interrupted at once. Outside the main thread the list stays
    empty."""
    got: list[int] = into if into is not None else []
    if not _main_thread():
        yield got
        return

    def request(signum, frame):
        if got:  # asked twice: stop now
            raise Interrupted(signum, "asked twice, stopped at once")
        got.append(signum)
        log.warning("%s: %s", signal.Signals(signum).name, what)

    with _handling(request):
        yield got
