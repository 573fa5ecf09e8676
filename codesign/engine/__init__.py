"""Experiments, I/O and plotting: everything that runs a job and writes a run directory."""
