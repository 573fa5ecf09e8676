"""The GPU campaign's CPU rehearsal (python -m benchmarks.gpu --dry-run): every step runs at tiny sizes and
reports what it measured; the GPU run's results and docs/gpu.md are left alone; bad arguments are refused."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from benchmarks import gpu
from codesign.train.checkpoint import check_trained, load_checkpoint

REPO = Path(__file__).resolve().parent.parent


@pytest.mark.slow  # 45 s: every campaign step; twin: test_a_partial_run_keeps_the_other_steps_results
def test_dry_run_runs_every_step_and_writes_its_own_folder(tmp_path):
    docs_before = gpu.DOCS.read_bytes() if gpu.DOCS.is_file() else None
    out = subprocess.run([sys.executable, "-m", "benchmarks.gpu", "--dry-run", "--out", str(tmp_path)],
                         capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    res = json.loads((tmp_path / "gpu.json").read_text())
    assert res["dry_run"] and set(res["seconds"]) == set(gpu.STEPS)
    assert res["tests"]["exit"] == 0 and res["tests"]["passed"] >= 10 and "failed" not in res["tests"]
    cells = res["speed"]["inference"]
    assert len(cells) == 2 * 2 * 2 and all("error" not in c and c["images_per_s"] > 0 for c in cells)
    joint = res["speed"]["joint"]
    assert joint["joint"]["total"] > 0 and joint["joint"]["mask_to_psf"] > 0 and joint["frozen"]["total"] > 0
    assert [r["samples_across"] for r in res["speed"]["psf"]] == [192]
    assert res["train"]["exit"] == 0 and res["train"]["steps"] == 4
    scores = res["evaluation"]["scores"]
    assert res["evaluation"]["exit"] == 0 and len(res["evaluation"]["evaluation_scenes"]) == 2
    for method in ("sgan", "sensor", "wiener"):
        for alpha in gpu.ALPHAS:
            assert all(math.isfinite(v) for v in scores[method][alpha].values()), (method, alpha)
    md = (tmp_path / "gpu.md").read_text()
    assert md.startswith("# GPU campaign (DRY RUN on a CPU at tiny sizes: not GPU figures)")
    assert "| sgan_f | tiny | bf16 | 2 |" in md and "Not run yet" not in md
    for name in ("inference.png", "restorations_1e6.png", "tests.log", "train.log", "evaluate.log"):
        assert (tmp_path / name).is_file(), name
    assert (gpu.DOCS.read_bytes() if gpu.DOCS.is_file() else None) == docs_before
    # the trained network travels as weights and config alone, which evaluate / restore / init.checkpoint read
    assert res["train"]["checkpoint"] == "checkpoint.pt"
    state = load_checkpoint(tmp_path / "checkpoint.pt")
    check_trained(state, "checkpoint.pt", "checkpoint")
    assert set(state) == {"model", "step", "config"} and state["step"] == 4
    # --render writes the page again from gpu.json alone, with the findings written by hand beside it
    (tmp_path / gpu.NOTES).write_text("## Findings\n\nA defect, fixed.\n")
    (tmp_path / "gpu.md").unlink()
    assert gpu.main(["--render", "--out", str(tmp_path)]) == 0
    again = (tmp_path / "gpu.md").read_text()
    assert again.replace("## Findings\n\nA defect, fixed.\n\n", "") == md and "A defect, fixed." in again
    assert (gpu.DOCS.read_bytes() if gpu.DOCS.is_file() else None) == docs_before


def test_compiled_cells_sgan_f_and_paper_width_first_at_the_largest_batch():
    plan = gpu.PLANS["gpu"]
    eager, compiled = gpu.inference_passes(plan), gpu.inference_passes(plan, compiled=True)
    assert len(eager) == len(compiled) == 6
    assert all(modes == ("float32", "bf16") and batches == (1, 8) for _, _, modes, batches in eager)
    assert all(modes == ("float32+cudagraphs", "float32+compile") and batches == (8,)
               for _, _, modes, batches in compiled)
    assert [(m, w) for m, w, _, _ in compiled[:2]] == [("sgan_f", "paper"), ("sgan_f", "cpu")]
    assert gpu.inference_passes(gpu.PLANS["dry"], compiled=True) == []



def test_a_short_compiled_call_adds_cells_and_keeps_the_earlier_ones():
    cell = lambda mode, **r: {"model": "sgan_f", "width": "paper", "mode": mode, "batch": 8, **r}  # noqa: E731
    old = [cell("float32", images_per_s=45.4), cell("float32+compile", images_per_s=55.7),
           cell("float32+cudagraphs", error="not run: speed budget spent")]
    new = [cell("float32+cudagraphs", images_per_s=59.2), cell("float32+compile", error="not run: speed budget spent"),
           {**cell("float32+compile"), "width": "cpu", "error": "not run: speed budget spent"}]
    merged = gpu.merge_compiled(old, new)
    assert merged == [old[0], new[0], old[1], new[2]]
    # a cell measured again replaces the earlier figure, a failure too
    again = gpu.merge_compiled(merged, [cell("float32+compile", error="OutOfMemoryError: CUDA")])
    assert again == [old[0], cell("float32+compile", error="OutOfMemoryError: CUDA")]

def test_recorded_commands_name_no_path_of_the_machine(tmp_path):
    """gpu.json goes into the repository: its commands and folders name the checkout's paths relative to it, the
    campaign's temporary folder as <tmp> and an --out outside the checkout as <out> (tests/test_repository.py)."""
    work, out = tmp_path / "codesign_gpu_x", tmp_path / "out"
    cmd = (f"python -m codesign +experiment=evaluate checkpoint={out}/checkpoint.pt data.folder={REPO.parent}/shared/"
           f"data/scenes hydra.run.dir={work}/evaluate init={REPO}/benchmarks/results/gpu/checkpoint.pt")
    assert gpu.portable(cmd, work, out) == ("python -m codesign +experiment=evaluate checkpoint=<out>/checkpoint.pt "
                                            "data.folder=../shared/data/scenes hydra.run.dir=<tmp>/evaluate "
                                            "init=benchmarks/results/gpu/checkpoint.pt")
    inside = REPO / "benchmarks" / "results" / "gpu"
    assert gpu.portable(f"checkpoint={inside}/checkpoint.pt", work, inside) == \
        "checkpoint=benchmarks/results/gpu/checkpoint.pt"


@pytest.mark.parametrize("args,message", [
    (["--dry-run"], "--dry-run needs --out DIR (its tiny-size figures must not replace the GPU results)"),
    (["--dry-run", "--out", "X", "--only", "tests,fly"], "--only 'tests,fly': allowed steps: tests, speed, compiled, "
                                                          "train, evaluate (comma-separated)"),
    (["--dry-run", "--out", "X", "--budget-min", "0.5"], "--budget-min 0.5: must be between 1 and 600"),
    (["--dry-run", "--out", "X", "--checkpoint", "nowhere.pt"], "--checkpoint nowhere.pt: no such file"),
    (["--render", "--out", "nowhere"], "--render: nowhere/gpu.json does not exist"),
])
def test_bad_arguments_are_refused_before_any_work(args, message, capsys):
    with pytest.raises(SystemExit) as stop:
        gpu.main(args)
    assert stop.value.code == 2 and message in capsys.readouterr().err


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_without_a_gpu_the_campaign_points_to_the_dry_run(capsys):
    with pytest.raises(SystemExit):
        gpu.main([])
    assert (f"no CUDA device visible (torch {torch.__version__}): run on a GPU node, or --dry-run on a CPU"
            in capsys.readouterr().err)
    with pytest.raises(SystemExit):
        gpu.main(["--profile"])
    assert f"--profile: no CUDA device visible (torch {torch.__version__}): it profiles the GPU" in capsys.readouterr().err


def test_a_partial_run_keeps_the_other_steps_results(tmp_path):
    (tmp_path / "gpu.json").write_text(json.dumps({"dry_run": True, "tests": {"exit": 0, "summary": "kept",
                                                                              "seconds": 1.0},
                                                    "seconds": {"tests": 1.0}, "machines": {}}))
    assert gpu.main(["--dry-run", "--out", str(tmp_path), "--only", "speed"]) == 0
    res = json.loads((tmp_path / "gpu.json").read_text())
    assert res["tests"]["summary"] == "kept" and "speed" in res and set(res["seconds"]) == {"tests", "speed"}
    md = (tmp_path / "gpu.md").read_text()
    assert "## 3. Training with the published mask\n\nNot run yet." in md
