"""SensorSimulator pipeline: background energy bookkeeping, output layout, skip paths, the kernel cache."""
from __future__ import annotations

import pytest
import torch

from codesign.optics import HalfRingMask
from codesign.optics.masks import PUBLISHED_R, PUBLISHED_THETA, published_halfring
from codesign.optics.metrics import bsr
from codesign.sensor.simulator import mask_state_key, psf_state
from . import _util as U

# (focal_n, resolution, image_size): with the 33-sample window the odd PSF kernel spans exactly the window at
# bin factor 1 (33 px) and 3 (11 px); with the brief's 32-sample window it spans 33 px (bin 1) or 36 px (bin 4).
BG_GEOMETRIES = [pytest.param(U.ODD, 9, 9, id="window33-bin1"),
                 pytest.param(U.ODD, 33, 11, id="window33-bin3"),
                 pytest.param(U.EVEN, 16, 16, id="window32-bin1"),
                 pytest.param(U.EVEN, 64, 16, id="window32-bin4")]


# ---- background -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("coded_psf", [True, False], ids=["coded", "uncoded"])
@pytest.mark.parametrize("focal_n,resolution,image_size", BG_GEOMETRIES)
def test_uniform_scene_irradiance_is_alpha_b_times_bsr(focal_n, resolution, image_size, coded_psf):
    """r_b = alpha_b (b * h) / sum(h0): a uniform white scene gives alpha_b sum(h) / sum(h0) = alpha_b BSR
    everywhere (alpha_b exactly for the uncoded PSF)."""
    coded, uncoded, h0 = U.states(focal_n)
    state = coded if coded_psf else uncoded
    sim = U.make_sim(focal_n, resolution, image_size, padded_size=image_size + 2)
    alpha_b = 0.6
    out = sim(U.uniform_scene(sim), U.params(alpha_b=alpha_b), state, seed=0)
    expect = alpha_b * float(bsr(state.psf, h0))
    irr = out["irradiance"]
    assert irr.shape == (1, 1, image_size + 2, image_size + 2)
    rel = float((irr / expect - 1).abs().max())
    assert rel < 1e-3, f"irradiance {float(irr.mean()):.6g} vs alpha_b BSR = {expect:.6g} (rel err {rel:.3g})"


@pytest.mark.parametrize("focal_n,resolution,image_size", [pytest.param(U.ODD, 33, 11, id="window33-bin3"),
                                                           pytest.param(U.EVEN, 64, 16, id="window32-bin4")])
def test_direct_and_full_paths_agree_on_a_uniform_scene(focal_n, resolution, image_size):
    """Noise off: both paths must give the same mean counts for a uniform scene (G e_sat alpha_b BSR)."""
    coded, _, h0 = U.states(focal_n)
    # padded_size = image_size + 4: the scene crop then also covers the full path's sensor-resolution support
    d = U.make_sim(focal_n, resolution, image_size, padded_size=image_size + 4, path="direct")
    f = U.make_sim(focal_n, resolution, image_size, padded_size=image_size + 4, path="full")
    p = U.params(alpha_b=0.7)
    dn_d = float(d(U.uniform_scene(d), p, coded, seed=0)["sensor_dn"].mean())
    dn_f = float(f(U.uniform_scene(f), p, coded, seed=0)["sensor_dn"].mean())
    expect = d.sensor.gain_dn_per_e * d.sensor.full_well_e * 0.7 * float(bsr(coded.psf, h0))
    assert abs(dn_d - expect) < 1.0 and abs(dn_f - expect) < 1.0, \
        f"mean counts: direct {dn_d:.2f}, full {dn_f:.2f}, expected G e_sat alpha_b BSR = {expect:.2f}"


@pytest.mark.parametrize("padded_size", [11, 12, 15])
def test_full_path_sensor_border_sees_the_scene(padded_size):
    """Full path, uniform white scene, noise off: every sensor pixel, the border included, reads G e_sat alpha_b
    BSR. (The scene crop is padded_size + ksize - 1 coarse pixels; padded_size may equal image_size.)"""
    coded, _, h0 = U.states(U.ODD)
    sim = U.make_sim(U.ODD, 33, 11, padded_size=padded_size, path="full")
    out = sim(U.uniform_scene(sim), U.params(alpha_b=0.7), coded, seed=0)
    expect = sim.sensor.gain_dn_per_e * sim.sensor.full_well_e * 0.7 * float(bsr(coded.psf, h0))
    dev = (out["sensor_dn"][0, 0] - expect).abs()
    worst = divmod(int(dev.argmax()), 11)
    assert float(dev.max()) < 1.0, f"pixel {worst} reads {float(out['sensor_dn'][0, 0][worst]):.2f} counts, " \
                                   f"expected {expect:.2f} (centre pixel: {float(out['sensor_dn'][0, 0, 5, 5]):.2f})"


def test_background_is_linear_in_alpha_b_and_the_scene():
    coded, _, _ = U.states(U.ODD)
    sim = U.make_sim(U.ODD, 33, 11, padded_size=13)
    a, b = U.random_scene(sim, seed=1), U.random_scene(sim, seed=2)
    irr = lambda s, ab: sim(s, U.params(alpha_b=ab), coded, seed=0)["irradiance"]  # noqa: E731
    torch.testing.assert_close(irr(0.3 * a + 0.5 * b, 1.0), 0.3 * irr(a, 1.0) + 0.5 * irr(b, 1.0),
                               rtol=1e-10, atol=1e-13)
    torch.testing.assert_close(irr(a, 0.7), 0.7 * irr(a, 1.0), rtol=1e-12, atol=0)


def test_point_scene_gives_the_kernel():
    """A single bright scene pixel spreads into the PSF kernel (pixel-integrated at the coarse pitch)."""
    from codesign.sensor import kernels
    coded, _, _ = U.states(U.ODD)
    sim = U.make_sim(U.ODD, 33, 11, padded_size=11)
    s, k = sim.scene_size, sim.coarse.ksize
    scene = torch.zeros(1, 1, s, s, dtype=torch.float64)
    scene[0, 0, s // 2, s // 2] = 1.0
    irr = sim(scene, U.params(alpha_b=1.0), coded, seed=0)["irradiance"][0, 0]
    kern = sim.kernel(coded) / coded.uncoded_energy
    # and the simulator's kernel is the window PSF integrated over the coarse pixel (same interpolant, up to the
    # zero padding of the window, which changes the truncated PSF's interpolant by ~1 % at this tiny window)
    alone = kernels.kernel(coded.psf, U.DX, k, sim.coarse.pitch, True) / coded.uncoded_energy
    torch.testing.assert_close(kern, alone, rtol=0.05, atol=1e-3 * float(alone.max()))
    # output pixel (i, j) sees scene pixel (i + k//2, j + k//2); the point is at output (s//2 - k//2, ...)
    c = s // 2 - k // 2
    torch.testing.assert_close(irr[c - k // 2: c + k // 2 + 1, c - k // 2: c + k // 2 + 1], kern,
                               rtol=1e-9, atol=1e-12)


# ---- outputs --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("path", ["direct", "full"])
def test_output_shapes_and_layout(path):
    coded, _, _ = U.states(U.ODD)
    sim = U.make_sim(U.ODD, 33, 11, padded_size=15, path=path)
    b = 2
    scene = U.random_scene(sim, batch=b)
    out = sim(scene, U.params(b, alpha_b=0.5, alpha_l=10.0, **U.NOISY), coded, seed=0)
    n, pad, k = 11, 15, sim.coarse.ksize
    assert set(out) == {"sensor_dn", "sensor", "irradiance", "scene", "saturated", "laser"}
    for key in ("sensor_dn", "saturated", "laser"):
        assert out[key].shape == (b, 1, n, n)
    for key in ("sensor", "irradiance", "scene"):
        assert out[key].shape == (b, 1, pad, pad)
    assert out["saturated"].dtype == torch.bool
    # the scene target is the central crop of the scene
    torch.testing.assert_close(out["scene"], scene[..., k // 2: k // 2 + pad, k // 2: k // 2 + pad], rtol=0, atol=0)
    # the network input is dn / (G e_sat), zero padded by (pad - n) // 2 = 2
    s = sim.sensor
    norm = out["sensor_dn"] / (s.gain_dn_per_e * s.full_well_e)
    torch.testing.assert_close(out["sensor"][..., 2:13, 2:13], norm, rtol=0, atol=0)
    border = out["sensor"].clone()
    border[..., 2:13, 2:13] = 0
    assert torch.equal(border, torch.zeros_like(border))


def test_wrong_scene_shape_is_rejected():
    coded, _, _ = U.states(U.ODD)
    sim = U.make_sim(U.ODD, 9, 9)
    s = sim.scene_size
    for shape in [(1, 1, s, s + 1), (1, 2, s, s), (s, s), (1, 1, s - 1, s - 1)]:
        with pytest.raises(ValueError, match="scene must have shape"):
            sim(torch.zeros(shape, dtype=torch.float64), U.params(), coded, seed=0)


def test_geometry_of_the_levels():
    sim = U.make_sim(U.EVEN, 64, 16, padded_size=20)
    assert sim.coarse.pitch == pytest.approx(4 * U.DX) and sim.coarse.bins == pytest.approx(16)
    assert sim.coarse.ksize == 9 and sim.scene_size == 20 + 9 - 1
    assert sim.fine.ksize == 33 and sim.fine.n_sensor == 64
    assert sim.coarse.noise_scale == pytest.approx(0.25)
    with pytest.raises(ValueError, match="focal_pitch_m"):
        from codesign.sensor.simulator import SensorSimulator
        from codesign.sensor.spec import SensorSpec
        SensorSimulator(SensorSpec(resolution=16, image_size=16, padded_size=16, pixel_pitch_m=5.0e-6),
                        U.optics(U.EVEN))


def test_same_seed_reproduces_and_seeds_differ():
    coded, _, _ = U.states(U.ODD)
    sim = U.make_sim(U.ODD, 33, 11)
    scene = U.random_scene(sim)
    p = U.params(alpha_b=0.5, alpha_l=50.0, **U.NOISY)
    a, b, c = (sim(scene, p, coded, seed=s)["sensor_dn"] for s in (3, 3, 4))
    assert torch.equal(a, b) and not torch.equal(a, c)


# ---- skip paths -----------------------------------------------------------------------------------------------
SKIP_CASES = {
    "alpha_l_0": dict(alpha_l=0.0, **U.NOISY),
    "laser_outside": dict(alpha_l=1e6, laser_angle_rad=0.05, **U.NOISY),
    "no_photon_noise": dict(alpha_l=30.0, c1=0.0, c2=0.0, dark_current_mean_e=0.002, read_noise_mean_e=390.0,
                            read_noise_std_e=10.5),
    "no_dark": dict(alpha_l=30.0, c1=0.2, c2=1.0, dark_current_mean_e=0.0, read_noise_mean_e=390.0,
                    read_noise_std_e=10.5),
    "no_read_std": dict(alpha_l=30.0, c1=0.2, c2=1.0, dark_current_mean_e=0.002, read_noise_mean_e=390.0,
                        read_noise_std_e=0.0),
    "all_noise_off": dict(alpha_l=30.0),
    "all_on": dict(alpha_l=30.0, **U.NOISY),
}


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("path", ["direct", "full"])
@pytest.mark.parametrize("case", list(SKIP_CASES))
def test_skipping_unneeded_terms_changes_nothing(path, case, dtype):
    coded, _, _ = U.states(U.ODD, dtype)
    fast = U.make_sim(U.ODD, 33, 11, path=path, skip_unneeded=True)
    ref = U.make_sim(U.ODD, 33, 11, path=path, skip_unneeded=False)
    scene = U.random_scene(fast, batch=2, dtype=dtype)
    p = U.params(2, dtype=dtype, alpha_b=0.5, **SKIP_CASES[case])
    a, b = fast(scene, p, coded, seed=9), ref(scene, p, coded, seed=9)
    for key in a:
        assert torch.equal(a[key], b[key]), \
            f"{key}: max |skip - reference| = {float((a[key].double() - b[key].double()).abs().max()):.3g}"


def test_skip_with_a_mixed_batch():
    """One sample without laser / photon noise, one with: the batch is simulated the same either way."""
    coded, _, _ = U.states(U.ODD)
    fast = U.make_sim(U.ODD, 33, 11, skip_unneeded=True)
    ref = U.make_sim(U.ODD, 33, 11, skip_unneeded=False)
    scene = U.random_scene(fast, batch=2)
    p = U.params(2, alpha_b=0.5, **U.NOISY).replace(alpha_l=torch.tensor([0.0, 100.0], dtype=torch.float64))
    a, b = fast(scene, p, coded, seed=1), ref(scene, p, coded, seed=1)
    for key in a:
        assert torch.equal(a[key], b[key]), key


# ---- kernel cache ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("path", ["direct", "full"])
def test_kernel_cache_for_a_frozen_mask(path):
    sysm, spec = U.system(U.ODD), U.optics(U.ODD)
    mask = published_halfring(sysm.grid, spec.aperture_diameter_m)
    key = mask_state_key(mask)
    assert key is not None
    sim = U.make_sim(U.ODD, 33, 11, path=path)
    scene = U.random_scene(sim)
    p = U.params(alpha_b=0.5, alpha_l=100.0, **U.NOISY)
    with torch.no_grad():
        state = psf_state(sysm, mask.phase())
    first = sim(scene, p, state, seed=2, mask_key=key)
    cached = dict(sim._cache)
    assert len(cached) == (1 if path == "direct" else 2) and all(k[0] == key for k in cached)
    second = sim(scene, p, state, seed=2, mask_key=key)
    assert all(sim._cache[k] is cached[k] for k in cached)  # reused, not recomputed
    uncached = sim(scene, p, state, seed=2, mask_key=None)
    for k in first:
        assert torch.equal(first[k], second[k]) and torch.equal(first[k], uncached[k]), k


def test_kernel_cache_follows_in_place_mask_changes():
    sysm, spec = U.system(U.ODD), U.optics(U.ODD)
    mask = HalfRingMask(sysm.grid, spec.aperture_diameter_m, PUBLISHED_R, PUBLISHED_THETA)
    for prm in mask.parameters():
        prm.requires_grad_(False)
    sim = U.make_sim(U.ODD, 33, 11)
    scene = U.random_scene(sim)
    p = U.params(alpha_b=0.5, alpha_l=100.0)
    key1 = mask_state_key(mask)
    out1 = sim(scene, p, psf_state(sysm, mask.phase()), seed=0, mask_key=key1)
    with torch.no_grad():
        mask.r.add_(0.5)
    key2 = mask_state_key(mask)
    assert key2 != key1
    state2 = psf_state(sysm, mask.phase())
    out2 = sim(scene, p, state2, seed=0, mask_key=key2)
    assert not torch.equal(out1["irradiance"], out2["irradiance"])
    assert list(sim._cache) == [(key2, sim.coarse.pitch)]  # the stale entry was dropped
    fresh = sim(scene, p, state2, seed=0, mask_key=None)
    for k in out2:
        assert torch.equal(out2[k], fresh[k]), k


def test_mask_state_key_is_none_while_training():
    sysm, spec = U.system(U.ODD), U.optics(U.ODD)
    mask = HalfRingMask(sysm.grid, spec.aperture_diameter_m)
    assert mask_state_key(mask) is None
    with torch.no_grad():
        assert mask_state_key(mask) is not None


def test_kernel_cache_key_sees_writes_through_data():
    """Writes through ``.data`` do not bump the version counter; the cache key hashes the values instead."""
    sysm, spec = U.system(U.ODD), U.optics(U.ODD)
    mask = published_halfring(sysm.grid, spec.aperture_diameter_m)
    key = mask_state_key(mask)
    mask.r.data.copy_(0.5 * mask.r.data)
    assert mask_state_key(mask) != key
    mask.r.data.copy_(2.0 * mask.r.data)
    assert mask_state_key(mask) == key  # same values, same key
