"""``python -m codesign +experiment=NAME``: the thin Hydra entry point. Work happens in codesign.experiments.

Under ``torchrun`` the process group is joined before Hydra composes the config, so that every rank agrees on
rank 0's run directory (codesign/train/distributed.py).
"""
from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from codesign.signals import Interrupted, interruptible

CONF_DIR = str(Path(__file__).resolve().parent.parent / "conf")


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="config")
def _hydra_main(cfg: DictConfig) -> float | None:
    from codesign.experiments import run_experiment

    return run_experiment(cfg)


def main() -> None:
    from codesign.config.runtime import renamed_key_error
    from codesign.train import distributed

    problem = renamed_key_error(sys.argv[1:])
    if problem:
        print(f"codesign: configuration error: {problem}", file=sys.stderr)
        raise SystemExit(2)
    # from here on SIGINT / SIGTERM raise Interrupted: run_experiment reports one during a run; one before it
    # (Hydra composing the config, the imports) or after it is reported here, without a traceback
    with interruptible():
        try:
            distributed.launch_setup(sys.argv[1:])
            try:
                _hydra_main()
            finally:
                distributed.finish()
        except Interrupted as stop:
            print(f"codesign: {stop.name}: stopped before the run started or after it ended", file=sys.stderr)
            raise SystemExit(stop.exit_code) from None


if __name__ == "__main__":
    main()
