#!/usr/bin/env bash
# Installs codesign and its dependencies (editable, with the test extra) into the current Python ($PYTHON, default
# python).
#   bash install.sh                      # connected machine
#   bash install.sh --wheelhouse DIR     # a node without a package registry: only from DIR, made on a connected
#                                        # machine by `python -m codesign.io.wheelhouse DIR` (docs/gpu.md)
# torch: an installed torch is kept, whatever its build. Otherwise torch==2.13.0 is installed from pip's own
# configuration (its index and find-links); a user who needs a particular build (CPU-only, a CUDA version) installs
# it first, or points pip's configuration at it, and this script keeps it. No package index is named here.
set -euo pipefail
cd "$(dirname "$0")"
PY="${PYTHON:-python}"
TORCH="torch==2.13.0"
WHEELHOUSE=""
if [ "${1:-}" = "--wheelhouse" ]; then
  WHEELHOUSE="${2:?install.sh --wheelhouse DIR: give the folder of wheels}"
  [ -d "$WHEELHOUSE" ] || { echo "install.sh: --wheelhouse $WHEELHOUSE: no such folder" >&2; exit 2; }
elif [ -n "${1:-}" ]; then
  echo "install.sh: unknown argument '$1'; allowed: --wheelhouse DIR (or nothing)" >&2; exit 2
fi
if [ -n "$WHEELHOUSE" ]; then
  "$PY" -c "import torch" 2>/dev/null || ls "$WHEELHOUSE"/torch-*.whl >/dev/null 2>&1 || {
    echo "install.sh: torch is not installed and $WHEELHOUSE holds no torch wheel (build it with --with-torch)" >&2
    exit 2; }
  # no network: every dependency, and the build backend of the editable install, from the folder or already
  # installed; codesign itself from this checkout
  "$PY" -m pip install -q --no-index --find-links "$WHEELHOUSE" -e ".[dev]"
else
  "$PY" -c "import torch" >/dev/null 2>&1 || "$PY" -m pip install "$TORCH"
  "$PY" -m pip install -q -e ".[dev]"
fi
"$PY" -c "import torch, codesign; cuda = torch.cuda.is_available(); print(f'codesign {codesign.__version__}, ' \
  f'torch {torch.__version__}, cuda ' + (f'{torch.version.cuda} on {torch.cuda.get_device_name(0)}' if cuda \
  else 'not available (CPU only)'))"
