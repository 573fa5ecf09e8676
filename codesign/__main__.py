"""``python -m codesign +experiment=NAME``: the thin Hydra entry point. Work happens in codesign.experiments.

Under ``torchrun`` the process group is joined before Hydra composes the config, so that every rank agrees on
rank 0's run directory (codesign/train/distributed.py).
"""
from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

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
    distributed.launch_setup(sys.argv[1:])
    try:
        _hydra_main()
    finally:
        distributed.finish()


if __name__ == "__main__":
    main()
