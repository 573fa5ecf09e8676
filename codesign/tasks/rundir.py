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

from codesign.errors import ConfigError
from codesign.io import files as io

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
        from codesign.train import distributed

        ctx = distributed.current()
        if ctx.is_main:  # under torchrun rank 0 alone writes, so it alone checks and records what was there
            _check(config, "hydra.run.dir")
        # ... before any other rank's Hydra creates the shared folder (which would look like an earlier run's)
        distributed.barrier(ctx)

    def on_multirun_start(self, config, **kwargs) -> None:  # runs before Hydra builds the launcher
        _check_launcher(config)
        _check(config, "hydra.sweep.dir")


# launcher class -> the pip package that provides it (the optional extra: pip install '.[launchers]')
LAUNCHER_PACKAGES = {"hydra_plugins.hydra_joblib_launcher": "hydra-joblib-launcher",
                     "hydra_plugins.hydra_submitit_launcher": "hydra-submitit-launcher"}


def _installed(module: str) -> bool:
    import importlib.util

    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:  # the parent package (the hydra_plugins namespace) is missing too
        return False


def _check_launcher(config) -> None:
    """A launcher config whose plugin is not installed: one line naming the package, not Hydra's traceback."""
    target = str(OmegaConf.select(config, "hydra.launcher._target_") or "")
    module = target.rsplit(".", 1)[0]
    for prefix, package in LAUNCHER_PACKAGES.items():
        if module.startswith(prefix) and not _installed(prefix):
            choice = OmegaConf.select(config, "hydra.runtime.choices")
            name = choice.get("hydra/launcher") if choice is not None else None
            print(f"codesign: configuration error: hydra/launcher = {name or target}: needs the optional plugin "
                  f"{package}: pip install {package} (or pip install '.[launchers]' in the repository)",
                  file=sys.stderr)
            raise SystemExit(2)
