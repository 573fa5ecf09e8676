#!/usr/bin/env bash
# Installs codesign and its dependencies (editable, with the test extra) into the current Python.
# torch: keep an installed torch; otherwise take torch==2.13.0, preferring a CPU build on a machine without an
# NVIDIA GPU (a local wheel when pip's find-links has one, else PyTorch's CPU index) so that a CPU-only machine
# never downloads the multi-GB CUDA wheels; on a GPU machine the registry's CUDA build is wanted.
set -euo pipefail
cd "$(dirname "$0")"
PY="${PYTHON:-python}"
TORCH="torch==2.13.0"
if ! "$PY" -c "import torch" >/dev/null 2>&1; then
  if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
    "$PY" -m pip install "$TORCH"
  elif "$PY" -m pip install --no-index --no-deps "$TORCH" >/dev/null 2>&1; then
    "$PY" -m pip install "$TORCH"   # the local CPU wheel is in place; this only adds torch's own dependencies
  else
    "$PY" -m pip install "$TORCH" --index-url https://download.pytorch.org/whl/cpu \
      --extra-index-url https://pypi.org/simple
  fi
fi
"$PY" -m pip install -q -e ".[dev]"
"$PY" -c "import torch, codesign; print(f'codesign {codesign.__version__}, torch {torch.__version__}, ' \
  f'cuda {torch.cuda.is_available()}')"
