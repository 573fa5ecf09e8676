"""trainer.amp / channels_last / compile, and the training step's freedom from host-device synchronization."""
from __future__ import annotations

import inspect
from pathlib import Path

import pytest
import torch
from torch.overrides import TorchFunctionMode

from codesign.train.spec import TrainerSpec
from codesign.errors import ConfigError
from codesign.models.wiener import LearnableWiener
from tests.train._util import tiny_trainer

NO_IO = dict(val_every=0, checkpoint_every=0, image_every=0)
CODESIGN = Path(__file__).resolve().parents[2] / "codesign"


def test_amp_accepts_null_and_bf16_only():
    assert TrainerSpec(amp="bf16").amp == "bf16" and TrainerSpec().amp is None
    with pytest.raises(ConfigError) as err:
        TrainerSpec(amp="fp16")
    assert str(err.value) == ("trainer.amp = 'fp16': must be null (float32) or bf16 (float16 would need loss "
                              "scaling; bfloat16 has float32's range)")
    with pytest.raises(ConfigError, match="trainer.compile = 'yes': must be true or false"):
        TrainerSpec(compile="yes")


@pytest.mark.parametrize("gamma", [1e-7, 1e-2, 10.0])
def test_wiener_division_stays_float32_under_bf16_autocast(gamma):
    """An OTF with exact zeros and a vanishing nsr: the worst case for an 8-bit mantissa. Under autocast the
    Wiener layer still computes in float32, bit for bit as without autocast, also when handed bf16 features."""
    torch.manual_seed(0)
    w = LearnableWiener(4, gamma_init=gamma)
    f = torch.randn(2, 4, 32, 32).to(torch.bfloat16)  # features as a bf16 layer hands them over
    otf = torch.fft.rfft2(torch.rand(32, 32))
    otf[3:9, 2:5] = 0
    ref = w(f.float(), otf)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got, got_bf16_in = w(f.float(), otf), w(f, otf)
    assert got.dtype == got_bf16_in.dtype == torch.float32
    assert torch.equal(got, ref) and torch.equal(got_bf16_in, ref) and torch.isfinite(ref).all()


def test_bf16_step_simulates_in_float32_and_returns_float32_losses(tmp_path):
    a = tiny_trainer(tmp_path / "a", steps=4, **NO_IO)
    b = tiny_trainer(tmp_path / "b", steps=4, amp="bf16", **NO_IO)
    # the optics and the sensor simulation run outside autocast: identical batches
    ba, bb = a.data.train_batch(0), b.data.train_batch(0)
    assert all(torch.equal(ba[k], bb[k]) for k in ("sensor", "irradiance", "scene"))
    assert bb["sensor"].dtype == torch.float32 and b.data.otf.dtype == torch.complex64
    out = b.update.generate(bb)
    assert out["i_b"].dtype == out["features"].dtype == out["b"][1].dtype == torch.float32
    for _ in range(3):
        terms = b.train_step()
    assert all(v.dtype == torch.float32 and torch.isfinite(v) for v in terms.values())
    assert b.skipped == 0


def test_channels_last_step_matches_the_default_layout(tmp_path):
    a = tiny_trainer(tmp_path / "a", steps=4, **NO_IO)
    b = tiny_trainer(tmp_path / "b", steps=4, channels_last=True, **NO_IO)
    assert b.model.g1.head[0][0].weight.is_contiguous(memory_format=torch.channels_last)
    ta, tb = a.train_step(), b.train_step()
    for k in ta:  # the same arithmetic in another memory order: float32 rounding apart
        assert float(tb[k]) == pytest.approx(float(ta[k]), rel=1e-4, abs=1e-5), k


@pytest.mark.slow
def test_compiled_generators_train_like_eager(tmp_path):
    a = tiny_trainer(tmp_path / "a", steps=4, **NO_IO)
    b = tiny_trainer(tmp_path / "b", steps=4, compile=True, **NO_IO)
    ta, tb = a.train_step(), b.train_step()
    for k in ta:
        assert float(tb[k]) == pytest.approx(float(ta[k]), rel=1e-3, abs=1e-5), k


# ---- no host-device synchronization in a step ------------------------------------------------------------------
SYNCING = {"item", "__bool__", "__float__", "__int__", "__index__", "tolist", "numpy"}
# Host-side decisions a step is allowed to make: the random draws on CPU generators (data/) and the simulator's
# decisions on the scene parameters, which the training data keeps on the host (sensor/; docs/scaling.md).
HOST_SIDE = ("data/", "sensor/")


class SyncRecorder(TorchFunctionMode):
    """Records every call that reads a tensor's value on the host, with the codesign file that made it."""

    def __init__(self):
        super().__init__()
        self.calls: list[tuple[str, str]] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", "")
        if name in SYNCING:
            for frame in inspect.stack()[1:]:
                path = Path(frame.filename).resolve()
                if CODESIGN in path.parents:
                    self.calls.append((name, str(path.relative_to(CODESIGN))))
                    break
        return func(*args, **(kwargs or {}))


def test_recorder_sees_the_calls_that_synchronize():
    with SyncRecorder() as rec:
        from codesign.train import distributed

        distributed.all_mean({"a": torch.tensor(1.0)}, distributed.SINGLE)
    assert ("tolist", "train/distributed.py") in rec.calls


def test_a_training_step_reads_no_device_value_outside_the_host_side_draws(tmp_path):
    tr = tiny_trainer(tmp_path, steps=4, ema=0.99, **NO_IO)
    tr.train_step()
    with SyncRecorder() as rec:
        tr.train_step()
        tr.train_step()
    offenders = sorted({c for c in rec.calls if not c[1].startswith(HOST_SIDE)})
    assert offenders == []
    assert rec.calls  # the host-side draws are seen (the recorder works inside the step)
