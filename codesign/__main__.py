"""``python -m codesign +experiment=NAME``: the thin Hydra entry point. Work happens in codesign.engine."""
from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

CONF_DIR = str(Path(__file__).resolve().parent.parent / "conf")


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="config")
def main(cfg: DictConfig) -> float | None:
    from codesign.engine.experiments import run_experiment

    return run_experiment(cfg)


if __name__ == "__main__":
    main()
