"""The tensor paths on the device the suite is pointed at: ``python -m pytest tests/device --device cuda`` on a GPU,
the CPU by default (then these run as the rest of the suite does).

Physics against float64 references computed on the CPU, with tolerances a float32 device must meet (a GPU that
computed float32 matrix products in TF32, 10 mantissa bits, would miss them by an order of magnitude); then the
training paths: a restoration step, a co-design step with the mask learnable, resume from a checkpoint, bf16
autocast, and (CUDA only) the sync-free step under torch.cuda.set_sync_debug_mode.
"""
from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import scipy.special
import torch

from codesign.models.wiener import classical_wiener
from codesign.optics import OpticalSystem, OpticsSpec, metrics
from codesign.optics.bessel import bessel_j
from codesign.optics.masks import published_halfring
from codesign.train.checkpoint import load_checkpoint
from codesign.train.evaluation import Evaluator
from tests.sensor import _util as S
from tests.train._util import joint_trainer, tiny_trainer

NO_IO = dict(val_every=0, checkpoint_every=0, image_every=0)


def _rel_l1(a: torch.Tensor, ref: torch.Tensor) -> float:
    a, ref = a.detach().to("cpu", torch.float64), ref.detach().to("cpu", torch.float64)
    return float((a - ref).abs().sum() / ref.abs().sum())


def _published_psf(samples: int, focal_n: int, propagator: str, dtype, dev) -> tuple[torch.Tensor, OpticalSystem]:
    spec = OpticsSpec.with_samples_across(samples, focal_n=focal_n, propagator=propagator)
    system = OpticalSystem(spec, dtype=dtype, device=dev)
    mask = published_halfring(system.grid, spec.aperture_diameter_m)
    with torch.no_grad():
        return system.psf(mask.phase()), system


@pytest.mark.parametrize("propagator", ["mft", "czt"])
def test_float32_psf_on_the_device_matches_the_float64_reference(device, propagator):
    ref, _ = _published_psf(96, 96, "mft", torch.float64, torch.device("cpu"))
    psf, system = _published_psf(96, 96, propagator, torch.float32, device)
    assert psf.device.type == device.type and psf.dtype == torch.float32
    assert _rel_l1(psf, ref) < 5e-5  # 1.85e-5 on the CPU (float32 phase); TF32-like rounding: 3.5e-4
    assert abs(float(psf.sum()) - float(ref.sum())) / float(ref.sum()) < 1e-5  # the window's energy
    lsr = metrics.lsr_sampled(psf, system.uncoded_peak)
    ref_sys = OpticalSystem(system.spec, dtype=torch.float64)
    assert float(lsr) == pytest.approx(float(metrics.lsr_sampled(ref, ref_sys.uncoded_peak)), rel=1e-5)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
def test_bessel_on_the_device_matches_scipy(device, dtype, tol):
    x = torch.linspace(0, 120, 997, dtype=torch.float64)
    got = bessel_j(x.to(device, dtype), 36)
    assert got.device.type == device.type and got.dtype == dtype
    ref = scipy.special.jv(np.arange(37)[None, :], x.numpy()[:, None])
    assert np.abs(got.cpu().double().numpy() - ref).max() < tol


def test_sensor_irradiance_on_the_device_matches_the_float64_cpu_simulation(device):
    sim64 = S.make_sim(S.ODD, 27, 27)
    coded64, _, _ = S.states(S.ODD, torch.float64)
    scene = S.random_scene(sim64, seed=3)
    ref = sim64(scene, S.params(1, alpha_b=0.5), coded64, seed=0)
    sim = S.make_sim(S.ODD, 27, 27).to(device)
    coded32, _, _ = S.states(S.ODD, torch.float32)
    state = dataclasses.replace(coded32, psf=coded32.psf.to(device))
    out = sim(scene.to(device, torch.float32), S.params(1, dtype=torch.float32, alpha_b=0.5), state, seed=0)
    assert out["irradiance"].device.type == device.type
    assert _rel_l1(out["irradiance"], ref["irradiance"]) < 2e-5  # 3.6e-6 on the CPU
    # a 1e8 laser saturates its spot and nothing turns non-finite on the device
    hot = sim(scene.to(device, torch.float32), S.params(1, dtype=torch.float32, alpha_l=1e8, **S.NOISY), state, seed=1)
    assert all(bool(torch.isfinite(v).all()) for v in hot.values() if v.is_floating_point())
    assert bool(hot["saturated"].any())


def test_classical_wiener_on_the_device_matches_float64(device):
    g = torch.Generator().manual_seed(0)
    y = torch.rand(2, 1, 64, 64, generator=g, dtype=torch.float64)
    psf, _ = _published_psf(96, 64, "mft", torch.float64, torch.device("cpu"))
    otf = torch.fft.rfft2(torch.fft.ifftshift(psf / psf.sum()))
    ref = classical_wiener(y, otf, 1e-2)
    got = classical_wiener(y.to(device, torch.float32), otf.to(device, torch.complex64), 1e-2)
    assert got.device.type == device.type and got.dtype == torch.float32
    assert float((got.cpu().double() - ref).abs().max()) < 1e-5 * float(ref.abs().max())  # 2.6e-7 on the CPU


def _on(module: torch.nn.Module, device: torch.device) -> bool:
    return all(p.device.type == device.type for p in module.parameters())


def test_a_training_step_runs_on_the_device_and_moves_the_generators(tmp_path, device):
    tr = tiny_trainer(tmp_path, steps=4, device=device, **NO_IO)
    assert _on(tr.model, device)
    before = [p.detach().clone() for g in tr.model.generators() for p in g.parameters()]
    terms = [tr.train_step() for _ in range(2)]
    assert all(v.device.type == device.type and bool(torch.isfinite(v)) for t in terms for v in t.values())
    after = [p.detach() for g in tr.model.generators() for p in g.parameters()]
    assert any(not torch.equal(a, b) for a, b in zip(before, after)) and tr.skipped == 0


def test_a_joint_step_moves_the_mask_on_the_device(tmp_path, device):
    tr = joint_trainer(tmp_path, device=device)
    assert _on(tr.codesign.mask, device)
    before = {n: p.detach().clone() for n, p in tr.codesign.mask.named_parameters()}
    for _ in range(2):
        terms = tr.train_step()
    assert all(bool(torch.isfinite(v)) for v in terms.values())
    moved = [n for n, p in tr.codesign.mask.named_parameters() if not torch.equal(p.detach(), before[n])]
    assert moved and all(bool(torch.isfinite(p).all()) for p in tr.codesign.mask.parameters())


def test_resume_on_the_device_continues_the_run(tmp_path, device):
    a = tiny_trainer(tmp_path / "a", steps=4, device=device, **NO_IO)
    a.train_step()
    a.train_step()
    path = a.save(tmp_path / "ck.pt")
    later = [a.train_step() for _ in range(2)]
    b = tiny_trainer(tmp_path / "b", steps=4, seed=123, device=device, **NO_IO)
    b.load_state_dict(load_checkpoint(path))
    assert b.step == 2 and _on(b.model, device)
    again = [b.train_step() for _ in range(2)]
    if device.type == "cpu":
        assert later == again  # bit for bit (tests/train/test_trainer.py)
    else:  # cuDNN may pick other convolution algorithms in another process: equal to float32 rounding
        for x, y in zip(later, again):
            for k in x:
                assert float(x[k]) == pytest.approx(float(y[k]), rel=1e-3, abs=1e-5), k


def test_bf16_autocast_step_on_the_device_keeps_float32_physics_and_losses(tmp_path, device):
    tr = tiny_trainer(tmp_path, steps=4, amp="bf16", device=device, **NO_IO)
    batch = tr.data.train_batch(0)
    assert batch["sensor"].dtype == torch.float32 and tr.data.otf.dtype == torch.complex64
    out = tr.update.generate(batch)
    assert out["i_b"].dtype == torch.float32
    terms = [tr.train_step() for _ in range(3)][-1]
    assert all(v.dtype == torch.float32 and bool(torch.isfinite(v)) for v in terms.values()) and tr.skipped == 0


def test_the_evaluation_tunes_and_scores_on_the_device(tmp_path, device):
    """The evaluator on the device: the first GPU campaign (2026-11-26) found its black-level offset built on the
    CPU (a per-image parameter) and subtracted from a CUDA image, which failed every evaluation on a GPU."""
    tr = tiny_trainer(tmp_path, device=device, **NO_IO)
    ev = Evaluator(tr.model, tr.model.generators(), tr.data, batch_size=8)
    ev.tune(tr.data.validation_batch(2))
    scenes = tr.data.source.fixed_batch(tr.data.source.split_names("test"), tr.data.camera.scene_size)
    batch = tr.data.preset_batch(scenes.to(device), "laser_1e6", seed=3)
    images = ev.restore_all(batch)
    assert all(x.device.type == device.type for x in images.values())
    table = ev.score(images, batch["scene"][..., 8:56, 8:56])
    assert all(np.isfinite(row["psnr_matched"]) and row["psnr_matched"] >= row["psnr"] - 1e-4 for row in table.values())


def test_a_training_step_never_synchronizes_with_the_gpu(tmp_path, device):
    if device.type != "cuda":
        pytest.skip("CUDA only (--device cuda); the CPU counterpart, which records every host read of a tensor, is "
                    "tests/train/test_train_options.py")
    tr = tiny_trainer(tmp_path, steps=8, ema=0.99, device=device, **NO_IO)
    tr.train_step()  # the first step logs (a host read by design), creates Adam's state and caches the optics
    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            tr.train_step()
            tr.train_step()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    # torch's own notice that the debug mode is a prototype is no synchronization; a real one says "called a
    # synchronizing CUDA operation"
    syncs = [str(w.message).splitlines()[0] for w in seen if "called a synchronizing" in str(w.message).lower()]
    assert syncs == []
