#!/usr/bin/env bash
# WienerUNet against SGAN-B on the same wall-clock budget (300 s of training each, same seed and data draws), then
# both evaluated on the 12 held-out photographs; run from the repository root, one at a time (2 CPU cores).
# metrics.json of each run is copied here as <model>.json (built-in test split) and <model>_shared12.json.
set -euo pipefail
for m in wiener_unet sgan_b; do
  python -m codesign +experiment=baseline model=$m trainer.steps=100000 trainer.time_budget_s=300 \
      logging.tensorboard=false hydra.run.dir=outputs/restorer_same_budget/$m
  python -m codesign +experiment=evaluate checkpoint=outputs/restorer_same_budget/$m/checkpoint.pt \
      data.scenes=folder data.folder=../shared/data/scenes evaluate.split=all \
      hydra.run.dir=outputs/restorer_same_budget/${m}_shared12
done
