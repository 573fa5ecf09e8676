#!/usr/bin/env bash
# The main job's network (SGAN-B, cpu width, 96 px padded to 128, batch 4, 160 steps: preset=joint_cpu
# trainer=joint_cpu) trained with the published mask, then evaluated on the 12 held-out photographs at alpha_l = 0,
# 1e3, 1e5, 1e6; one arm per residual setting (docs/models.md Sec. 10). Run from the repository root, one at a time.
set -euo pipefail
declare -A ARMS=([default]="" [g2res]="model.g2_residual=true" [filled]="model.g2_residual=true model.g1_base=filled")
for arm in default g2res filled; do
  d=outputs/early_steps/$arm
  python -m codesign +experiment=baseline preset=joint_cpu trainer=joint_cpu seed=0 ${ARMS[$arm]} \
      logging.tensorboard=false evaluate.stages=[] evaluate.max_scenes=2 evaluate.laser_strengths=[0] \
      hydra.run.dir=$d/train
  python -m codesign +experiment=evaluate checkpoint=$d/train/checkpoint.pt data.scenes=folder \
      data.folder=../shared/data/scenes evaluate.split=all evaluate.stages=[] "evaluate.laser_strengths=[0,1e3,1e5,1e6]" \
      hydra.run.dir=$d/eval
  cp $d/eval/metrics.json benchmarks/results/early_steps/${arm}_shared12.json
done
