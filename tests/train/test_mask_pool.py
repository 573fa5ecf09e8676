"""data.masks: a restorer's training batches through a pool of frozen masks, each batch with its own mask's OTF."""
from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from codesign.errors import ConfigError
from codesign.experiments.evaluate import merged_eval_config
from codesign.train import checkpoint as ckpt
from codesign.train.data import build_simulated_data
from codesign.train.mask_pool import MaskPool, build_mask_pool
from tests.train._util import CPU, tiny_cfg

POOL = "data.masks=[published,defocus:20,defocus:50]"


@pytest.fixture(scope="module")
def pooled():
    cfg = tiny_cfg(POOL, "data.mask_draws=1", "data.mask_jitter=0.1", "data.mask_every=3")
    data = build_simulated_data(cfg, CPU, 0)
    data.use_pool(build_mask_pool(cfg, data.camera, 0))
    return cfg, data


def test_pool_holds_every_member_and_its_draws(pooled):
    _, data = pooled
    assert data.pool.names == ["published", "published draw 1", "defocus:20", "defocus:20 draw 1", "defocus:50",
                               "defocus:50 draw 1"]
    lsr = dict(zip(data.pool.names, data.pool.lsr()))
    # a stronger defocus spreads the focal spot over more pixels: a lower peak
    assert lsr["defocus:50"] < lsr["defocus:20"] < lsr["published"]
    for cam in data.pool.cameras:  # every member frozen, its optics on the shared optical system
        assert cam.system is data.camera.system
        assert not any(p.requires_grad for p in cam.mask.parameters())


def test_draws_scatter_around_their_member_by_the_jitter_within_bounds(pooled):
    _, data = pooled
    cams = dict(zip(data.pool.names, data.pool.cameras))
    base, drawn = cams["defocus:50"].mask.to_vector(), cams["defocus:50 draw 1"].mask.to_vector()
    lo, hi = cams["defocus:50 draw 1"].mask.bounds()
    assert bool(((drawn >= lo) & (drawn <= hi)).all())
    spread = float((drawn - base).square().mean().sqrt() / base.square().mean().sqrt())
    assert 0.08 < spread < 0.12  # the jitter 0.1, over the spline's many control values


def test_member_of_a_step_depends_on_seed_and_window_alone():
    pool = MaskPool([str(k) for k in range(5)], [None] * 5, every=3, seed=7)
    picks = [pool.index(s) for s in range(300)]
    assert picks == [MaskPool([str(k) for k in range(5)], [None] * 5, 3, 7).index(s) for s in range(300)]
    assert all(picks[s] == picks[s - s % 3] for s in range(300))  # one member per window of mask_every steps
    assert set(picks) == set(range(5))
    assert picks != [MaskPool([str(k) for k in range(5)], [None] * 5, 3, 8).index(s) for s in range(300)]


def test_training_batch_carries_its_members_otf_and_validation_keeps_the_configured_mask(pooled):
    _, data = pooled
    members = set()
    for step in range(0, 30, 3):
        cam = data.pool.camera(step)
        members.add(id(cam))
        assert torch.equal(data.train_batch(step)["otf"], cam.otf)
    assert len(members) > 1  # the batches come through several masks
    assert torch.equal(data.otf, data.camera.otf)
    assert "otf" not in data.validation_batch(2)


def test_pool_batch_equals_a_direct_simulation_through_the_member():
    cfg = tiny_cfg(POOL, "data.mask_every=1")
    a, b = build_simulated_data(cfg, CPU, 3), build_simulated_data(cfg, CPU, 3)
    a.use_pool(build_mask_pool(cfg, a.camera, 3))
    pool = build_mask_pool(cfg, b.camera, 3)
    for step in range(4):
        got = a.train_batch(step)
        want = b.simulate(*b.train_draw(step), camera=pool.camera(step))
        assert torch.equal(got["sensor"], want["sensor"])
        assert torch.equal(got["otf"], pool.camera(step).otf)


def test_trainable_mask_refuses_a_pool(pooled):
    cfg, data = pooled
    other = build_simulated_data(cfg, CPU, 0)
    other.camera.set_trainable(True)
    with pytest.raises(ConfigError, match="trains a restorer over frozen masks"):
        other.use_pool(data.pool)


def test_evaluate_takes_a_typed_mask_over_the_checkpoints(pooled):
    cfg, _ = pooled
    here = OmegaConf.merge(cfg, {"mask": {"kind": "spline"}})
    kept = merged_eval_config(here, cfg, frozenset())
    assert kept.mask.kind == cfg.mask.kind
    typed = merged_eval_config(here, cfg, frozenset({"mask"}))
    assert typed.mask.kind == "spline"


def test_shipped_checkpoint_is_found_by_name_or_named_as_missing(tmp_path, monkeypatch):
    assert ckpt.checkpoint_path("some/run/checkpoint.pt") == ckpt.Path("some/run/checkpoint.pt")
    monkeypatch.setattr(ckpt, "PRETRAINED_DIR", tmp_path)
    with pytest.raises(ConfigError) as err:
        ckpt.load_checkpoint("pretrained", "init.checkpoint")
    assert str(err.value) == (f"init.checkpoint = 'pretrained': names the shipped restorer "
                              f"{tmp_path / ckpt.PRETRAINED['pretrained']}, which this installation lacks (reinstall "
                              "codesign, or give a checkpoint path)")


def test_random_family_members_lie_in_the_lsr_range_and_repeat_for_a_seed():
    cfg = tiny_cfg("data.masks=[random:zernike:2,random:halfring,random:pixel]", "data.mask_lsr=[1e-3,2e-2]")
    data = build_simulated_data(cfg, CPU, 0)
    pool = build_mask_pool(cfg, data.camera, 0)
    assert [n.split(" (")[0] for n in pool.names] == ["random:zernike 1", "random:zernike 2", "random:halfring 1",
                                                      "random:pixel 1"]
    assert all(1e-3 <= v <= 2e-2 for v in pool.lsr())
    assert [c.mask.kind for c in pool.cameras] == ["zernike", "zernike", "halfring", "pixel"]
    again = build_mask_pool(cfg, data.camera, 0)
    assert all(torch.equal(a.mask.to_vector(), b.mask.to_vector()) for a, b in zip(pool.cameras, again.cameras))
    other = build_mask_pool(cfg, data.camera, 1)
    assert not torch.equal(pool.cameras[0].mask.to_vector(), other.cameras[0].mask.to_vector())


@pytest.mark.parametrize("item", ["random:cube", "random:spline:0", "random:spline:x", "random:"])
def test_a_bad_random_member_is_named(item):
    cfg = tiny_cfg(f"data.masks=[published,'{item}']")
    data = build_simulated_data(cfg, CPU, 0)
    with pytest.raises(ConfigError, match=rf"^data\.masks\[1\] = '{item}': a random member is 'random:FAMILY' or "
                       r"'random:FAMILY:N', FAMILY one of halfring, pixel, spiral, spline, zernike"):
        build_mask_pool(cfg, data.camera, 0)


def test_pixel_scales_bin_the_same_sensor_and_pad_for_the_kernel():
    """data.scales: each member at every scale S, a crop of data.image_size px of the sensor binned to S px a side:
    the same pitch, a network pixel of resolution / S sensor pixels, and padding that holds the kernel."""
    cfg = tiny_cfg("data.masks=[published]", "data.scales=[48,96,192]", "data.mask_every=1")
    data = build_simulated_data(cfg, CPU, 0)
    pool = build_mask_pool(cfg, data.camera, 0)
    data.use_pool(pool)
    assert pool.names == ["published @ 48 px", "published @ 96 px", "published @ 192 px"]
    full = data.camera.sensor
    for cam, scale in zip(pool.cameras, (48, 96, 192)):
        s = cam.sensor
        assert s.pixel_pitch_m == full.pixel_pitch_m and s.image_size == full.image_size
        assert abs(s.coarse_pitch_m - full.pixel_pitch_m * full.resolution / scale) < 0.01 * s.coarse_pitch_m
        assert s.padded_size >= s.image_size + cam.simulator.coarse.ksize - 1 and s.padded_size % 8 == 0
    assert pool.cameras[0].sensor == full  # the run's own scale is the run's sensor
    kernels = [c.simulator.coarse.ksize for c in pool.cameras]
    assert kernels[0] < kernels[1] < kernels[2]  # a finer pixel: the PSF spans more of them
    for step in range(6):
        cam, batch = pool.camera(step), data.train_batch(step)
        p = cam.padded_size
        assert batch["sensor"].shape[-2:] == (p, p) and batch["otf"].shape == (p, p // 2 + 1)


def test_pixel_scales_are_checked():
    cfg = tiny_cfg("data.scales=[48,96]")
    data = build_simulated_data(cfg, CPU, 0)
    with pytest.raises(ConfigError, match=r"^data\.scales = \[48, 96\]: trains over pixel scales with a pool of "
                       r"masks: set data.masks too \(e\.g\. \[published\]\), or leave data\.scales null$"):
        build_mask_pool(cfg, data.camera, 0)
    cfg = tiny_cfg("data.masks=[published]", "data.scales=[48,3000]")
    data = build_simulated_data(cfg, CPU, 0)
    with pytest.raises(ConfigError, match=r"^data\.scales = 3000: must be <= sensor\.resolution \(2532\)"):
        build_mask_pool(cfg, data.camera, 0)
    with pytest.raises(ConfigError, match=r"^data\.scales = \[48, 48\]: must be a non-empty list of integer pixel "
                       r"scales in \[8, sensor\.resolution\], or null \(each scale once\)$"):
        build_simulated_data(tiny_cfg("data.scales=[48,48]"), CPU, 0)


def test_finer_scales_reuse_the_far_psf_of_the_coarsest_whose_sensor_is_largest():
    """One far PSF per mask (seconds each): the finer scales' smaller sensors take the coarsest scale's, which also
    keeps the light that falls beyond a small sensor out of it, as on the large sensor it is a crop of (a far plane
    of the small sensor's own reach squeezes that light into it: more saturated pixels)."""
    from codesign.data.params import preset_params

    cfg = tiny_cfg("data.masks=[published]", "data.scales=[48,192]", "sensor.laser_halo=true")
    data = build_simulated_data(cfg, CPU, 0)
    coarse, fine = build_mask_pool(cfg, data.camera, 0).cameras
    assert fine.halo_donor is coarse and coarse.halo_donor is None
    scenes = data.sampler.sample(None, fine.scene_size)
    params = preset_params("laser_1e6", scenes.shape[0])
    shared = fine(scenes, params, 5)["sensor"]
    assert fine._halo_frozen["halo"][1] is coarse._halo_frozen["halo"][1]
    own = build_mask_pool(tiny_cfg("data.masks=[published]", "data.scales=[192]", "sensor.laser_halo=true"),
                          data.camera, 0).cameras[0]
    alone = own(scenes, params, 5)["sensor"]
    saturated = lambda x: float((x >= 0.999).float().mean())  # noqa: E731
    assert 0.2 < saturated(shared) < saturated(alone)  # measured 0.343 and 0.461


def test_the_pool_shines_its_lasers_at_every_configured_line():
    """optics.laser_wavelengths_m: each member also at each laser line, the laser's PSF the mask's surface seen
    there (a line off the design wavelength has its own), the scene at the design wavelength as ever."""
    from codesign.data.params import preset_params

    cfg = tiny_cfg("data.masks=[published]", "optics.laser_wavelengths_m=[633e-9,532e-9]", "data.mask_every=1")
    data = build_simulated_data(cfg, CPU, 0)
    pool = build_mask_pool(cfg, data.camera, 0)
    assert pool.names == ["published @ laser 633 nm", "published @ laser 532 nm"]
    red, green = pool.cameras
    assert red.laser_line is None and green.laser_line is not None
    assert green.sensor.wavelength_laser_m == 532e-9 and red.sensor.wavelength_laser_m == 633e-9
    assert torch.equal(red.otf, green.otf)  # the restorer's OTF: the scene's, at the design wavelength
    scenes = data.sampler.sample(None, red.scene_size)
    params = preset_params("laser_1e6", scenes.shape[0])
    assert not torch.equal(red(scenes, params, 3)["sensor"], green(scenes, params, 3)["sensor"])


def test_a_released_member_images_the_same_when_it_serves_again():
    """Only the imaging member keeps its kernels and PSF spectra (tens of MB each); the others drop them and
    recompute them, identical, when drawn again."""
    from codesign.data.params import preset_params

    cfg = tiny_cfg(POOL, "data.mask_every=1")
    data = build_simulated_data(cfg, CPU, 0)
    pool = build_mask_pool(cfg, data.camera, 0)
    assert all(not c.simulator._cache for c in pool.cameras)  # released after the pool's optics were computed
    first = pool.cameras[pool.index(0)]
    other = next(s for s in range(1, 50) if pool.cameras[pool.index(s)] is not first)
    scenes = data.sampler.sample(None, first.scene_size)
    params = preset_params("laser_1e6", scenes.shape[0])
    before = pool.camera(0)(scenes, params, 3)["sensor"]
    assert first.simulator._cache
    pool.camera(other)
    assert not first.simulator._cache
    again = pool.camera(0)(scenes, params, 3)["sensor"]
    assert torch.equal(before, again)
