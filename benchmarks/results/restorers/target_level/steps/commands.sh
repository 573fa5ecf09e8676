# docs/models.md Sec. 13, "With steps": one training of the L1 recipe for 3,200 steps (seed 0, the published mask), its
# checkpoint copied every 400 steps (the level head is fitted at the end only: it sets plain PSNR, not the matched one),
# each copy scored on the 12 photographs. 2026-11-28, the 2-core AMD EPYC VM, 2 threads, torch 2.13.0+cpu.
python -m codesign +experiment=baseline model=sgan_b_gated preset=joint_cpu trainer=joint_cpu trainer.steps=3200 \
  data.batch_size=4 seed=0 threads=2 device=cpu mask=halfring trainer.val_every=3200 trainer.image_every=0 \
  trainer.checkpoint_every=400 'evaluate.laser_strengths=[0]' 'evaluate.stages=[]' evaluate.max_scenes=1 \
  logging.tensorboard=false hydra.run.dir=RUN model.g2_gate=false data.params.alpha_l_spacing=log \
  model.target_level=exposure model.loss.adv=0 model.loss.mdf=0
# after each checkpoint (N = 400, 800, ..., 3200), a copy of RUN/checkpoint.pt as ckpt_N.pt, then
python -m benchmarks.pretrained_eval --checkpoint ckpt_N.pt --masks published --threads 2 --out eval_stepN.json
# then resumed from the 3,200-step checkpoint in a new run folder (after the fix of the objective under a fitted level
# head, commit 2ae30c2): the schedule of a 4,800-step run (rate 2e-4 from 3,200 to 3,600, then halved)
python -m codesign ... (the same overrides) trainer.steps=4800 trainer.resume=ckpt_3200.pt trainer.val_every=4800 \
  hydra.run.dir=RUN2
python -m benchmarks.pretrained_eval --checkpoint ckpt_N.pt --masks published --threads 2 --out eval_stepN.json  # N = 4000, 4800
# then resumed again in RUN2 (its own checkpoint) with trainer.steps=6400 (the rate stays halved from 4,800), and
python -m benchmarks.pretrained_eval --checkpoint ckpt_6400.pt --masks published --threads 2 --out eval_step6400.json
