"""The run directory before Hydra touches it: writable, and what an earlier run left there kept safe.

Hydra creates the run dir and writes .hydra/ before our task function starts, so an unwritable hydra.run.dir
would otherwise end in Hydra's own traceback. ``OutputDirCheck`` (registered in conf/config.yaml under
hydra.callbacks) runs first: it refuses an unwritable folder with a configuration error, and remembers whether
the run dir already existed and what its .hydra/ held, so that a run stopped by a configuration error neither
deletes an earlier run's folder nor leaves that run's recorded config overwritten by the refused one.
"""
from __future__ import annotations

import shutil
import sys
from pathlib import Path

from omegaconf import OmegaConf

from codesign.engine import io
from codesign.errors import ConfigError

# absolute run dir that existed before this run -> {file name in its .hydra/: bytes}, or None without a .hydra/
EARLIER: dict[Path, dict[str, bytes] | None] = {}


def remember(run_dir: Path) -> None:
    """Record that ``run_dir`` exists already, with the contents of its .hydra/ (small YAML files)."""
    run_dir = Path(run_dir).absolute()
    if run_dir.is_dir():
        hydra_dir = run_dir / ".hydra"
        EARLIER[run_dir] = {f.name: f.read_bytes() for f in sorted(hydra_dir.glob("*.yaml")) if f.is_file()} \
            if hydra_dir.is_dir() else None


def existed_before(run_dir: Path) -> bool:
    return Path(run_dir).absolute() in EARLIER


def restore_earlier(run_dir: Path) -> None:
    """Put ``run_dir``'s .hydra/ back as the earlier run left it (Hydra rewrote it for the refused run)."""
    files = EARLIER.get(Path(run_dir).absolute())
    hydra_dir = Path(run_dir) / ".hydra"
    if files is None:  # the folder had no .hydra/: remove the one the refused run added
        shutil.rmtree(hydra_dir, ignore_errors=True)
        return
    for name, data in files.items():
        io.atomic_write_bytes(hydra_dir / name, lambda f, d=data: f.write(d))


def _check(config, key: str) -> None:
    folder = OmegaConf.select(config, key)
    try:
        io.check_writable_dir(Path(str(folder)), key)
    except ConfigError as err:
        print(f"codesign: configuration error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    remember(Path(str(folder)))


try:
    from hydra.experimental.callback import Callback
except ImportError:  # pragma: no cover - Hydra < 1.1
    Callback = object


class OutputDirCheck(Callback):
    def on_run_start(self, config, **kwargs) -> None:
        _check(config, "hydra.run.dir")

    def on_multirun_start(self, config, **kwargs) -> None:
        _check(config, "hydra.sweep.dir")
