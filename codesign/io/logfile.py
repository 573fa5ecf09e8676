"""The run's log file, opened without following a symbolic link: Hydra's job log (``hydra.job_logging``'s file
handler, conf/config.yaml) appends to ``<run dir>/<job>.log``; a link swapped in there after the run folder was
guarded (codesign/experiments/runlinks.py) would send the log into a file outside the folder. Opened with
O_NOFOLLOW, such a link fails the open instead."""
from __future__ import annotations

import logging
import os


class NoFollowFileHandler(logging.FileHandler):
    """logging.FileHandler (append) whose file is never reached through a symlink."""

    def _open(self):
        flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | getattr(os, "O_NOFOLLOW", 0)
        fd = os.open(self.baseFilename, flags, 0o644)
        return open(fd, "a", encoding=self.encoding, errors=self.errors)
