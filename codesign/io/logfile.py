"""The files written into a run folder before the experiment starts, opened without following a symbolic link: Hydra's
job log (``hydra.job_logging``'s file handler, conf/config.yaml) appends to ``<run dir>/<job>.log``, and the run's
record of its config (.hydra/config.yaml, hydra.yaml, overrides.yaml: written by codesign, runstart.py, in place of
Hydra's plain open). A link swapped in there after the run folder was guarded (codesign/experiments/runlinks.py)
would send them into a file or folder outside the run folder; opened with O_NOFOLLOW, such a link fails the open
instead."""
from __future__ import annotations

import logging
import os
from pathlib import Path


class NoFollowFileHandler(logging.FileHandler):
    """logging.FileHandler (append) whose file is never reached through a symlink."""

    def _open(self):
        flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | getattr(os, "O_NOFOLLOW", 0)
        fd = os.open(self.baseFilename, flags, 0o644)
        return open(fd, "a", encoding=self.encoding, errors=self.errors)


NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)


def write_text_nofollow(folder: Path, name: str, text: str) -> Path:
    """Write ``text`` to ``folder``/``name`` (created, or truncated), neither ``folder`` (its last part: created
    when missing) nor the file reached through a symbolic link: an OSError (ELOOP, ENOTDIR) instead. The path
    leading to ``folder`` may pass through links, as a run folder's may."""
    folder = Path(folder)
    try:
        os.mkdir(folder)
    except FileExistsError:  # a folder already, or a link: the open below refuses the link
        pass
    dir_fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | NOFOLLOW)
    try:
        fd = os.open(name, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | NOFOLLOW, 0o644, dir_fd=dir_fd)
    finally:
        os.close(dir_fd)
    with open(fd, "w", encoding="utf-8") as f:
        f.write(text)
    return folder / name
