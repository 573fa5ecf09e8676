"""Training: the trainer (owns every optimizer), co-design trainer, simulated data stream, evaluation,
checkpoints, resume and data parallelism."""
