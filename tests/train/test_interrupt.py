"""Ctrl-C and SIGTERM during training: the step in progress finishes, a checkpoint is written, one line says how to
resume, the exit status is 128 + the signal (130 / 143); the printed command continues the run to its end."""
from __future__ import annotations

import json
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from codesign.train.checkpoint import load_checkpoint

REPO = Path(__file__).resolve().parents[2]


def _args(steps: int) -> list[str]:
    return ["+experiment=baseline", "debug=smoke", f"trainer.steps={steps}", "trainer.checkpoint_every=1000",
            "trainer.val_every=1000", "logging.log_every=1"]


ARGS = _args(400)


def _start_and_wait_for_step_2(run_dir: Path, steps: int, timeout: float = 120.0) -> subprocess.Popen:
    """Start ``python -m codesign _args(steps)`` and return it once its log shows step 2."""
    proc = subprocess.Popen([sys.executable, "-m", "codesign", *_args(steps), f"hydra.run.dir={run_dir}"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    log, t_end = run_dir / "__main__.log", time.time() + timeout
    while time.time() < t_end:
        if proc.poll() is not None:
            raise AssertionError(f"ended before training: {proc.communicate()[1][-2000:]}")
        if log.is_file() and f" - step 2/{steps}" in log.read_text():
            return proc
        time.sleep(0.1)
    proc.kill()
    raise AssertionError("no training step within the timeout")


@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_checkpoints_at_the_next_step_and_exits_with_its_code(tmp_path, sig, code):
    run = tmp_path / "run"
    proc = _start_and_wait_for_step_2(run, 400)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err[-3000:]
    lines = [line for line in err.splitlines() if line.startswith("codesign: ")]
    assert len(lines) == 1 and "Traceback" not in err, err[-3000:]
    name = signal.Signals(sig).name
    assert lines[0].startswith(f"codesign: {name} at step ")
    assert lines[0].endswith(f"; resume with: python -m codesign {' '.join(ARGS)} hydra.run.dir={run}")
    step = int(lines[0].split(" at step ")[1].split()[0])
    state = load_checkpoint(run / "checkpoint.pt")
    assert state["step"] == step and 2 <= step < 400
    assert not (run / "metrics.json").exists()  # nothing claims the run finished


@pytest.mark.slow  # 20 s: an interrupted and a resumed process; twin: test_a_signal_checkpoints_at_the_next_step_and_exits_with_its_code
def test_the_printed_command_resumes_the_run_to_its_end(tmp_path):
    run = tmp_path / "run"
    proc = _start_and_wait_for_step_2(run, 12)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    if proc.returncode == 0:
        pytest.skip("the run finished before the signal arrived (a fast machine)")
    assert proc.returncode == 130, err[-3000:]
    command = err.strip().splitlines()[-1].split("resume with: ")[1]
    argv = shlex.split(command)
    assert argv[:3] == ["python", "-m", "codesign"]
    done = subprocess.run([sys.executable, *argv[1:]], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["steps"] == 12
    assert torch.is_tensor(load_checkpoint(run / "checkpoint.pt")["rng"]["torch"])
