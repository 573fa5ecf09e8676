"""The laser's light beyond the optics window (issue 16 item 7): the far PSF's halo conserves energy, is placed
exactly at any sub-pixel spot, is computed only when a laser needs it, and gives the saturated area of a float64
reference of the whole sensor within 5 %, where the window alone misses most of it."""
from __future__ import annotations

import pytest
import torch

from benchmarks import bench_laser_halo as bench
from codesign.camera import camera as camera_module
from codesign.camera.build import build_camera
from codesign.data.params import fixed_scene_params
from codesign.sensor.halo import LaserHalo
from tests.inputs._run import compose_cfg

# smoke optics (160-sample window, 0.86 mm) on a 640-pixel sensor (3.46 mm): most of the sensor lies beyond the
# window, as on the full-size camera
SMALL = ["optics.pupil_pitch_m=2.0e-5", "optics.focal_n=160", "sensor.resolution=640", "data.image_size=64",
         "data.padded_size=96"]


def _camera(*overrides):
    return build_camera(compose_cfg("+experiment=simulate", *SMALL, *overrides), torch.device("cpu"))


def test_the_halo_holds_the_far_psf_outside_the_window_and_unit_energy():
    g = torch.Generator().manual_seed(0)
    far = torch.rand(64, 64, generator=g, dtype=torch.float64)
    far /= far.sum()
    pitch = 1e-6
    halo = LaserHalo(far, pitch, (-8.5e-6, 7.5e-6))  # the window square: samples -8 .. 7 around the axis
    # pixels of 2 samples exactly on the sample grid, covering the whole far plane: all of the (unit) energy
    e = halo.pixel_energy((0.5e-6, 0.5e-6), 32, 2e-6)
    assert float(e.sum()) == pytest.approx(1.0, abs=1e-12)
    assert float(e[12:20, 12:20].abs().max()) < 1e-15  # the window square is the footprint's, not the halo's
    outside = far.clone()
    outside[24:40, 24:40] = 0
    assert halo.far_energy == pytest.approx(float(outside.sum()), rel=1e-12)
    # a sub-pixel shift moves light between pixels and keeps it on a grid that still holds the plane
    shifted = halo.pixel_energy((0.37e-6, -0.81e-6), 40, 2e-6)
    assert float(shifted.sum()) == pytest.approx(1.0, abs=1e-12)
    assert not torch.allclose(shifted[4:36, 4:36], e)


def test_a_pixel_receives_the_box_integral_of_the_far_samples():
    far = torch.zeros(16, 16, dtype=torch.float64)
    far[2, 3] = 1.0  # one cell: [-6.5, -5.5] x [-5.5, -4.5] sample pitches around the axis
    halo = LaserHalo(far, 1.0, (-1.0, 1.0))
    e = halo.pixel_energy((0.0, 0.0), 4, 3.0)  # pixel edges at -6, -3, 0, 3, 6
    # the cell [-6.5, -5.5] in y straddles the edge -6: half of it falls on the grid; in x [-5.5, -4.5] lies in
    # the first column [-6, -3] entirely
    assert float(e[0, 0]) == pytest.approx(0.5, abs=1e-12) and float(e.sum()) == pytest.approx(0.5, abs=1e-12)


def test_the_halo_is_computed_only_when_a_laser_needs_it_and_once_per_frozen_mask(monkeypatch):
    calls = []
    real = camera_module.far_psf
    monkeypatch.setattr(camera_module, "far_psf", lambda *a, **k: calls.append(1) or real(*a, **k))
    cam = _camera()
    sim, optics = cam.simulator, cam.frozen_optics()
    scene = torch.full((2, 1, sim.scene_size, sim.scene_size), 0.5)
    with torch.no_grad():
        sim(scene, fixed_scene_params(2, alpha_l=0.0), optics.state, seed=0, mask_key=optics.key)
        assert calls == []  # no laser: no far PSF
        for _ in range(2):
            sim(scene, fixed_scene_params(2, alpha_l=1e6), optics.state, seed=0, mask_key=optics.key)
        cam.invalidate()
        again = cam.frozen_optics()  # the same mask values: the same key, the same halo
        sim(scene, fixed_scene_params(2, alpha_l=1e6), again.state, seed=0, mask_key=again.key)
    assert calls == [1]


# Half the default sensor (1280 px, 6.9 mm: the window holds the core, the halo saturates beyond it) on a design
# pupil grid twice as fine as the default: on the default grid the window PSF's dark zone 0.4-1.2 mm from the spot
# is 2-3x too bright (its own sampling, not the halo's), which on this smaller sensor alone moves the area by 13 %
# at alpha_l = 1e6 (4 % on the full sensor: docs/sensor.md Sec. 7)
HALF = ["optics.pupil_pitch_m=4.987e-6", "sensor.resolution=1280", "data.image_size=128", "data.padded_size=192"]
HALF_ANGLE = (0.008 * 1280 / 2532, -0.012 * 1280 / 2532)  # the simulate experiment's spot, scaled with the sensor


def test_saturated_area_matches_a_float64_reference_of_the_whole_sensor():
    cfg = lambda *o: compose_cfg("+experiment=simulate", *HALF, *o)  # noqa: E731
    cam, without = build_camera(cfg(), torch.device("cpu")), build_camera(cfg("sensor.laser_halo=false"), "cpu")
    table, _ = bench.rows(cam, (1e5, 1e6, 2e6), refine=2, angle=HALF_ANGLE, without_halo=without)
    for r in table:
        assert abs(r["relative_error"]) < 0.05, r
    # what the window alone gave: the saturated area stopped growing at the window's edge
    strong = table[-1]
    assert strong["model_without_halo"] < 0.7 * strong["reference"]
    assert table[0]["model"] < table[1]["model"] < table[2]["model"]


def test_a_spot_beyond_the_sensor_still_lights_it_with_its_halo():
    cam = _camera()
    sim, optics = cam.simulator, cam.frozen_optics()
    scene = torch.zeros(1, 1, sim.scene_size, sim.scene_size)
    far_off = [0.03, 0.0]  # 3.3 mm to the side: the window footprint misses the 3.46 mm sensor
    with torch.no_grad():
        out = sim(scene, fixed_scene_params(1, alpha_l=1e7, laser_angle_rad=far_off, **bench.NOISE_FREE),
                  optics.state, seed=0, mask_key=optics.key)
    assert float(out["laser"].max()) > 0.0


def test_a_training_mask_refreshes_its_halo_every_halo_refresh_evaluations(monkeypatch):
    calls = []
    real = camera_module.far_psf
    monkeypatch.setattr(camera_module, "far_psf", lambda *a, **k: calls.append(1) or real(*a, **k))
    cam = _camera("sensor.halo_refresh=3")
    cam.set_trainable(True)
    for _ in range(7):  # optics evaluations 1..7, each with a laser: the far PSF at the 1st, 4th and 7th
        cam.current_optics().state.halo()
    assert calls == [1, 1, 1]
    # validation (frozen_optics of the training mask) shares the training halo instead of computing its own
    cam.invalidate()
    cam.frozen_optics().state.halo()
    assert calls == [1, 1, 1]
    # a checkpoint keeps the schedule and the values the halo came from: a resumed camera continues it
    state = cam.halo_state()
    assert state["age"] == 2
    other = _camera("sensor.halo_refresh=3")
    other.set_trainable(True)
    other.load_halo_state(state)
    other.current_optics().state.halo()  # the 3rd evaluation of this halo: recomputed from the saved values
    assert calls == [1, 1, 1, 1] and other.halo_state()["age"] == 3
