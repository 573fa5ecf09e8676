"""Data-parallel training under torchrun (gloo, 2 CPU processes) against one process on the same global batch.

The 2-process tests start real torchrun jobs (about 15 s each on 2 cores); the others check the pieces that make
a distributed step equal the single-process one: the batch shares, the per-sample noise, the GP draws.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

from codesign.config import resolvers
from codesign.train import distributed
from codesign.train.distributed import DistContext
from codesign.train.data import build_simulated_data
from codesign.errors import ConfigError
from tests.cli import run_codesign, run_torchrun
from tests.train._util import CPU, tiny_cfg

WORKER = str(Path(__file__).with_name("ddp_worker.py"))


def _out(res) -> str:
    return f"rc {res.returncode}\nstdout:\n{res.stdout[-3000:]}\nstderr:\n{res.stderr[-3000:]}"


# ---- the shares of a global batch -----------------------------------------------------------------------------
def test_rank_shares_of_a_training_batch_are_the_single_process_batch():
    cfg = tiny_cfg("data.batch_size=4")
    whole = build_simulated_data(cfg, CPU, 3).train_batch(5)
    shares = [build_simulated_data(cfg, CPU, 3, DistContext(r, 2, r)).train_batch(5) for r in range(2)]
    for key in ("scene", "irradiance", "sensor", "saturated"):
        joined = torch.cat([s[key] for s in shares])
        assert joined.shape == whole[key].shape
        assert torch.allclose(joined.double(), whole[key].double(), rtol=0, atol=1e-6), key
    # noise included: the sensor images differ between samples, and sample 2 is rank 1's first
    assert torch.equal(shares[1]["sensor"][0], shares[1]["sensor"][0]) and not torch.equal(
        shares[0]["sensor"][0], shares[1]["sensor"][0])


def test_a_samples_noise_does_not_depend_on_its_batch():
    from codesign.sensor.noise import NoiseStreams

    like = torch.zeros(3, 1, 5, 5)
    whole = NoiseStreams([10, 11, 12], CPU).normal("read", like)
    alone = NoiseStreams([11], CPU).normal("read", like[:1])
    assert torch.equal(whole[1:2], alone) and not torch.equal(whole[0], whole[1])
    with pytest.raises(ValueError, match="3 per-sample noise seeds for a batch of 2"):
        NoiseStreams([1, 2, 3], CPU).normal("read", like[:2])


def test_global_batch_must_split_evenly():
    with pytest.raises(ConfigError) as err:
        build_simulated_data(tiny_cfg("data.batch_size=2"), CPU, 0, DistContext(0, 3, 0))
    assert str(err.value) == ("data.batch_size = 2: must be divisible by the number of processes (3): it is the "
                              "global batch, split evenly across the ranks")


def test_resolvers_give_rank_zero_the_files(monkeypatch):
    for k in ("RANK", "WORLD_SIZE", resolvers.STAMP_ENV):
        monkeypatch.delenv(k, raising=False)
    assert resolvers.rank_suffix() == "" and resolvers.main_only(".hydra") == ".hydra"
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    assert resolvers.rank_suffix() == ".rank1" and resolvers.main_only(".hydra") is None
    monkeypatch.setenv(resolvers.STAMP_ENV, "2026-01-02_03-04-05_000006")
    assert resolvers.run_stamp() == "2026-01-02_03-04-05_000006"


# ---- real torchrun jobs ---------------------------------------------------------------------------------------
def test_two_gloo_ranks_hold_identical_mask_and_weights_and_match_one_process(tmp_path):
    """3 co-design steps, mask trainable from the first, global batch 4: on 2 ranks (2 + 2) and in one process."""
    res = run_torchrun(WORKER, str(tmp_path), "3")
    assert res.returncode == 0, _out(res)
    import subprocess

    single = subprocess.run([sys.executable, WORKER, str(tmp_path), "3"], capture_output=True, text=True,
                            timeout=300, env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    assert single.returncode == 0, single.stderr[-3000:]
    r0, r1, one = (torch.load(tmp_path / f"{n}.pt") for n in ("rank0", "rank1", "single"))
    assert r0["world"] == r1["world"] == 2 and one["world"] == 1
    # the replicas: bit-identical networks and mask on both ranks (DDP-averaged gradients, identical updates)
    assert r0["params"].keys() == r1["params"].keys() and len(r0["params"]) > 10
    assert all(torch.equal(r0["params"][k], r1["params"][k]) for k in r0["params"])
    assert r0["mask"] == r1["mask"] and r0["divergence"] == r1["divergence"] == 0.0
    # against one process on the same global batch: the first step's losses (same weights, same batch) to
    # float32 rounding [measured 1e-7], the second's to 1e-4 [measured 7e-6 on the generator terms]
    first, first1 = r0["losses"][0], one["losses"][0]
    assert first.keys() == first1.keys()
    for k in first:
        assert first[k] == pytest.approx(first1[k], rel=1e-5, abs=1e-6), k
    assert {"generator_total", "lsr_penalty"} <= first.keys()  # the main job's network and the mask's constraint
    for k in first:
        assert r0["losses"][1][k] == pytest.approx(one["losses"][1][k], rel=1e-4, abs=1e-6), k
    # ... and the mask after 3 steps [measured 2.6e-5 relative]: the GAN's updates amplify rounding, so the
    # networks are only compared loosely [measured 1.3e-3 absolute]
    for k, v in one["mask"].items():
        assert r0["mask"][k] == pytest.approx(v, rel=1e-3), k
    assert max((r0["params"][k] - one["params"][k]).abs().max().item() for k in one["params"]) < 2e-2


@pytest.mark.slow  # 26 s: torchrun joint + resume; twin: test_seeded_runs_reproduce_and_resume_continues_exactly
def test_torchrun_joint_writes_from_rank_zero_and_resumes_in_one_process(tmp_path):
    run_dir = tmp_path / "run"
    common = ["+experiment=joint", "codesign.protocol=single", "debug=smoke", "threads=1",
              "codesign.compare_published=false",
              "codesign.warmup_fraction=0", "data.batch_size=4", f"hydra.run.dir={run_dir}"]
    res = run_torchrun("-m", "codesign", *common, "trainer.steps=4", "trainer.checkpoint_every=4")
    assert res.returncode == 0, _out(res)
    m = json.loads((run_dir / "metrics.json").read_text())
    assert m["world_size"] == 2 and m["global_batch"] == 4 and m["steps"] == 4
    assert m["mask_max_rank_difference"] == 0.0 and m["parameters_max_rank_difference"] == 0.0
    # rank 0 alone wrote: one checkpoint, one .hydra/, one event file; rank 1 has its (warnings-only) log
    assert sorted(p.name for p in (run_dir / ".hydra").iterdir()) == ["config.yaml", "hydra.yaml",
                                                                       "overrides.yaml"]
    assert len(list(run_dir.glob("events.out.tfevents.*"))) == 1
    assert (run_dir / "__main__.rank1.log").is_file() and "step 4/4" in (run_dir / "__main__.log").read_text()
    assert "ranks=2 (gloo)" in (run_dir / "__main__.log").read_text()
    # resume across a change of world size: one process continues the 2-process checkpoint to step 6
    res = run_codesign(*common, "trainer.steps=6", timeout=300)
    assert res.returncode == 0, _out(res)
    log = (run_dir / "__main__.log").read_text()
    assert "at step 4 (written by 2 process(es), resumed by 1)" in log
    m = json.loads((run_dir / "metrics.json").read_text())
    assert m["world_size"] == 1 and m["steps"] == 6


@pytest.mark.slow  # 9 s: torchrun; twin: test_a_distributed_run_of_an_experiment_that_does_not_train_is_refused
def test_torchrun_refuses_experiments_that_do_not_train(tmp_path):
    res = run_torchrun("-m", "codesign", "+experiment=psf", "debug=smoke", f"hydra.run.dir={tmp_path / 'r'}")
    assert res.returncode != 0
    assert ("codesign: configuration error: task = 'psf': does not train networks and runs in one process: start it "
            "without torchrun (training experiments under torchrun: baseline, joint)") in res.stderr
    assert not (tmp_path / "r").exists()
    res = run_torchrun("-m", "codesign", "-m", "+experiment=baseline", "debug=smoke", "seed=0,1")
    assert res.returncode != 0 and "codesign: configuration error: -m/--multirun cannot run under torchrun" in \
        res.stderr


def test_a_distributed_run_of_an_experiment_that_does_not_train_is_refused(tmp_path, monkeypatch, capsys):
    """In process, as rank 0 of 2 (the torchrun job is the slow level's): the same refusal, before any work."""
    import codesign.experiments as experiments
    from tests.inputs._run import compose_cfg

    monkeypatch.setattr(experiments.distributed, "current", lambda: distributed.DistContext(0, 2, 0))
    with pytest.raises(SystemExit) as info:
        experiments.run_experiment(compose_cfg("+experiment=psf", "debug=smoke"), run_dir=tmp_path / "r")
    assert info.value.code == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "codesign: configuration error: task = 'psf': does not train networks and runs in one process: start it "
        "without torchrun (training experiments under torchrun: baseline, joint)")
    assert not (tmp_path / "r").exists()


def test_a_sweep_under_torchrun_is_refused_before_the_process_group(monkeypatch, capsys):
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    with pytest.raises(SystemExit) as info:
        distributed.launch_setup(["-m", "+experiment=baseline", "seed=0,1"])
    assert info.value.code == 2
    assert "codesign: configuration error: -m/--multirun cannot run under torchrun" in capsys.readouterr().err
