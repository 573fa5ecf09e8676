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

# After the per-condition tuning of the baselines (commit ed986ce): in-process arms of the filled base, 160 steps,
# scored at chosen steps on the 12 photographs at alpha_l = 0 and 1e6 (docs/results_log.md, "Since then")
R=benchmarks/results/early_steps
F="model.g2_residual=true model.g1_base=filled"
python -m benchmarks.early_steps --steps 160 --at 0,40,160 --out $R/filled.json $F
python -m benchmarks.early_steps --steps 160 --at 0,40,160 --out $R/filled_ema0.999.json $F trainer.ema=0.999
python -m benchmarks.early_steps --steps 160 --at 0,40,160 --out $R/filled_ema0.99.json $F trainer.ema=0.99
python -m benchmarks.early_steps --steps 160 --at 0,10,40,160 --out $R/filled_wienerbase.json $F model.g2_base=wiener
python -m benchmarks.early_steps --steps 160 --at 0,10,40,160 --out $R/filled_wienerbase_ema0.999.json $F \
    model.g2_base=wiener trainer.ema=0.999
# on the H100 (one device call, cut by its limit after step 400; Wiener there by the old rule)
python -m benchmarks.early_steps --device cuda --steps 5000 --at 0,10,30,100,200,400,700,1000,1500,2000,3000,4000,5000 \
    --out $R/gpu_filled_h100.json $F

# Third session (2026-11-27): model.laser_gate (G1's correction and the Wiener base's nsr follow the presence of
# saturated pixels), with the Wiener base and EMA 0.999; the lasered nsr from 0.03 or from 100 (the value the
# per-condition tuning picks for Wiener at alpha_l = 1e6); docs/results_log.md, "Then"
G="$F model.g2_base=wiener trainer.ema=0.999 model.laser_gate=true"
python -m benchmarks.early_steps --steps 160 --at 0,40,160 --out $R/filled_wienerbase_ema0.999_gate.json $G
python -m benchmarks.early_steps --steps 160 --at 0,40,160 --out $R/filled_wienerbase_ema0.999_gate_nsr100.json $G \
    model.g2_base_nsr_lasered=100
python -m benchmarks.early_steps --steps 160 --at 0,40,160 --out $R/filled_wienerbase_ema0.999_gate_nsr100_lr5e-5.json \
    $G model.g2_base_nsr_lasered=100 trainer.lr_weights=5e-5 trainer.lr_biases=1e-4
python -m benchmarks.early_steps --steps 160 --at 0,40,160 --out $R/filled_wienerbase_ema0.999_gate_nsr100_recon.json \
    $G model.g2_base_nsr_lasered=100 model.loss.adv=0 model.loss.mdf=0

# On the H100 (2026-11-27, one device call, cut by its limit after step 500): the gate + lasered-nsr arm
python -m benchmarks.early_steps --device cuda --steps 2000 --at 0,40,160,300,500,700,1000,1500,2000 \
    --out $R/gpu_gate_nsr100_h100.json $G model.g2_base_nsr_lasered=100

# Fourth session (2026-11-27). From here early_steps' MAIN_JOB is the new main job's network (model=sgan_b_gated,
# trainer=joint_cpu with EMA 0.99), and G2's Wiener base has unit DC gain: the lines above ran with model=sgan_b and
# no EMA and the old base (rerun them with `model=sgan_b trainer.ema=null` added; the base change is not optional).
# Diagnostics with the old base (the first two; g2_base_gain was an option of that session, measured, removed):
G="$F model.g2_base=wiener trainer.ema=0.999 model.laser_gate=true model.g2_base_nsr_lasered=100"
python -m benchmarks.early_steps --steps 160 --at 0,40,160 --out $R/filled_wienerbase_ema0.999_gate_nsr100_alphab0.7.json \
    $G "data.params.alpha_b_range=[0.7,0.7]" data.params.exposure_std_s=0
# python -m benchmarks.early_steps --steps 160 --at 0,10,40,160 \
#     --out $R/filled_wienerbase_ema0.999_gate_nsr100_alphab0.7_gain1.43.json $G model.g2_base_gain=1.4286 \
#     "data.params.alpha_b_range=[0.7,0.7]" data.params.exposure_std_s=0
# unit-DC base (model=sgan_b: g2_gate off)
python -m benchmarks.early_steps --steps 160 --at 0,10,40,160 \
    --out $R/filled_wienerbase_ema0.999_gate_nsr100_unitdc.json model=sgan_b $G
python -m benchmarks.early_steps --steps 160 --at 0,40,160 --out $R/filled_wienerbase_ema0.99_gate_nsr100_unitdc.json \
    model=sgan_b $G trainer.ema=0.99
# on the H100 (cut by the device call after step 300)
python -m benchmarks.early_steps --device cuda --steps 1000 --at 0,160,300,400,500,700,1000 \
    --out $R/gpu_unitdc_h100.json model=sgan_b $G
# the new default, model=sgan_b_gated with EMA 0.99 (the same as $G trainer.ema=0.99 model.g2_gate=true), two seeds
P="--presets laser_0,laser_1e3,laser_1e5,laser_1e6"
python -m benchmarks.early_steps --steps 160 --at 0,40,160 $P --out $R/unitdc_gate_g2gate_ema0.99.json
python -m benchmarks.early_steps --steps 160 --at 0,160 $P --out $R/unitdc_gate_g2gate_ema0.99_seed1.json seed=1
# the laser-strength spacing (2026-11-27, fifth session): the paper's linear grid over [0, 2e6] against
# data.params.alpha_l_spacing=log, on the published mask and on the spline design of the mask search
S="mask=spline mask.init=benchmarks/results/full/design/spline/best_mask.json.gz"
python -m benchmarks.early_steps --steps 160 --at 0,160 $P --out $R/gated_spline.json $S
python -m benchmarks.early_steps --steps 160 --at 0,160 $P --out $R/gated_spline_logalpha.json $S data.params.alpha_l_spacing=log
python -m benchmarks.early_steps --steps 160 --at 0,160 $P --out $R/gated_logalpha.json data.params.alpha_l_spacing=log
