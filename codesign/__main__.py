"""``python -m codesign +experiment=NAME``: the thin Hydra entry point. Work happens in codesign.experiments.

``--help`` / ``-h`` prints codesign's own help (the experiments from their modules' EXPERIMENT summaries) and
``--version`` codesign's version, both before Hydra runs; ``--hydra-help``, ``--cfg job``, ``-m`` and the other flags
are Hydra's. Before Hydra reads the overrides, a leading ``~`` of hydra.run.dir / hydra.sweep.dir is expanded and an
override Hydra cannot parse is reported with Hydra's message and a hint on quoting (codesign/config/argv.py).

Under ``torchrun`` the process group is joined before Hydra composes the config, so that every rank agrees on
rank 0's run directory (codesign/train/distributed.py).
"""
from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from codesign.config import CONF_DIR
from codesign.signals import Interrupted, interruptible


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def _hydra_main(cfg: DictConfig) -> float | None:
    from codesign.experiments import run_experiment

    return run_experiment(cfg)


def help_text() -> str:
    """codesign's ``--help``: the usage, every registered experiment with its summary, the set-up commands and where
    to read on."""
    from codesign.experiments import EXPERIMENTS, protocol

    width = max(len(name) for name in EXPERIMENTS)
    listing = "\n".join(f"  {name:<{width}}  {protocol(name).summary}" for name in EXPERIMENTS)
    return f"""usage: python -m codesign +experiment=NAME [group=option ...] [group.key=value ...] [hydra flags]
       codesign +experiment=NAME ...   (the same, as the installed console command)

Experiments (+experiment=NAME; the + is needed: `experiment` is not in the default config):
{listing}

Set up and run (fresh machine):
  bash install.sh && python -m codesign +experiment=joint     # the main job: mask + network co-design
  bash install.sh && python -m pytest -q                      # the tests

Examples:
  python -m codesign +experiment=psf mask=pixel               # choose a group's option
  python -m codesign +experiment=joint debug=smoke            # any experiment shrunk to seconds on a CPU
  python -m codesign +experiment=joint --cfg job              # print the composed config, run nothing

Read on:
  python -m codesign +experiment=NAME --cfg job   every key of a run with its value
  docs/config.md                                  every config key: default, meaning, units
  README.md                                       the docs index: every feature, its command and its docs/ page

Other flags:
  --version         print codesign's version
  --hydra-help      Hydra's own help (-m multirun sweeps, --cfg, --info, overrides grammar)
"""


def main() -> None:
    """The console command (``codesign``, ``python -m codesign``): --version and --help answered here, a renamed key
    refused, anything else run by the Hydra entry point on the command line's overrides."""
    from codesign.config.argv import expand_run_dirs, hydra_write_path_error, override_parse_problem
    from codesign.config.runtime import renamed_key_error
    from codesign.train import distributed

    args = sys.argv[1:]
    if "--version" in args:
        from importlib.metadata import PackageNotFoundError, version

        try:  # the installed distribution's (a wheel's, pip install .'s); a bare checkout falls back to the package's
            number = version("codesign")
        except PackageNotFoundError:
            from codesign import __version__ as number

        print(f"codesign {number}")
        raise SystemExit(0)
    if "--help" in args or "-h" in args:
        print(help_text(), end="")
        raise SystemExit(0)
    problem = renamed_key_error(sys.argv[1:]) or hydra_write_path_error(sys.argv[1:])
    if problem:
        print(f"codesign: configuration error: {problem}", file=sys.stderr)
        raise SystemExit(2)
    sys.argv[1:] = expand_run_dirs(sys.argv[1:])  # ~ in hydra.run.dir / hydra.sweep.dir, as in every path key
    unparsed = override_parse_problem(sys.argv[1:])
    if unparsed:  # Hydra's message, then the hint; Hydra's exit status
        print(unparsed, file=sys.stderr)
        raise SystemExit(1)
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
