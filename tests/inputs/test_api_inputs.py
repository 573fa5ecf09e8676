"""The Python API (codesign/api.py) checks its arguments as the command line checks its keys: a wrong one is a
ConfigError naming the function and the argument, the value and what is allowed, raised before any work (it was
accepted, or an AttributeError / RuntimeError from deep inside)."""
from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from codesign import api
from codesign.errors import ConfigError


@pytest.fixture(scope="module")
def cfg():
    return api.compose("debug=smoke")


@pytest.mark.parametrize("kwargs,message", [
    ({"seed": -5}, "sensor_image seed = -5: must be an integer >= 0 and <= 1e+09 (the noise seed, as the command "
                   "line's seed)"),  # was accepted (the command line refuses seed=-1)
    ({"seed": 1.5}, "sensor_image seed = 1.5: must be an integer >= 0 and <= 1e+09"),
    ({"alpha_l": 1e300}, "sensor_image alpha_l = 1e+300: must be a finite number >= 0 and <= 1e+12 (the laser "
                         "strength, as simulate.laser_strengths)"),  # was a RuntimeError (float overflow)
    ({"cam": "camera"}, "sensor_image cam = 'camera': must be a Camera (codesign.build_camera(cfg)) or None"),
    ({"cfg": "debug=smoke"}, "sensor_image cfg = 'debug=smoke': must be a configuration (codesign.compose(...)) or "
                             "None"),
], ids=["seed-negative", "seed-fraction", "alpha-huge", "cam", "cfg"])
def test_sensor_image_arguments(cfg, kwargs, message):
    with pytest.raises(ConfigError, match="^" + re.escape(message)):
        api.sensor_image(**{"cfg": cfg, **kwargs})


@pytest.mark.parametrize("kwargs,message", [
    ({"mask": "published"}, "psf_and_lsr mask = 'published': must be a Mask (codesign.published_mask(), "
                            "configured_mask(cfg), build_mask(...)) or None (the published mask)"),
    ({"system": 3}, "psf_and_lsr system = 3: must be an OpticalSystem (codesign.optical_system(cfg)) or None"),
], ids=["mask-name", "system"])
def test_psf_and_lsr_arguments(cfg, kwargs, message):
    # mask='published' was an AttributeError ('str' object has no attribute 'grid')
    with pytest.raises(ConfigError, match="^" + re.escape(message) + "$"):
        api.psf_and_lsr(**{"cfg": cfg, **kwargs})


def test_a_mask_built_on_another_grid_s_precision_is_sampled_onto_the_system_s(cfg):
    # a mask built on a float64 grid (optical_system(dtype=torch.float64)) ended in a RuntimeError ("Expected object
    # of scalar type Float but got scalar type Double") in psf_and_lsr and in a camera's images
    mask = api.configured_mask(cfg, api.optical_system(cfg, dtype=torch.float64))
    out = api.psf_and_lsr(mask, cfg=cfg)
    same = api.psf_and_lsr(api.configured_mask(cfg), cfg=cfg)
    assert out["lsr"] == pytest.approx(same["lsr"], rel=1e-4)
    cam = api.build_camera(cfg, mask=mask)
    assert cam.mask.grid.rho.dtype == torch.float32


# ---- issue 59 item 3: one row per call of the audit; each raises a one-line ConfigError naming the function and the
# argument, before any work (a run's checks come before its composition, a device's before any tensor is made)

def _experiments_never_run(monkeypatch):
    import codesign.experiments as experiments

    def started(*args, **kwargs):
        raise AssertionError("the experiment ran: the call should have been refused before it")
    monkeypatch.setattr(experiments, "run_experiment", started)


NO_CUDA = "CUDA is not available on this machine"
API_CALLS = {  # id: (call(cfg, tmp_path), the message's start)
    "run-unknown-experiment": (lambda c, d: api.run("nosuch", "debug=smoke", run_dir=d),
                               "run experiment = 'nosuch': must be one of baseline, evaluate, export, joint, "),
    "run-experiment-case": (lambda c, d: api.run("PSF", "debug=smoke", run_dir=d), "run experiment = 'PSF': must be"),
    "compose-unknown-experiment": (lambda c, d: api.compose(experiment="nosuch"), "compose experiment = 'nosuch': "
                                   "must be one of baseline"),
    "run-override-number": (lambda c, d: api.run("psf", 5, run_dir=d), "run override = 5: must be a string "
                            "'key=value'"),
    "run-override-none": (lambda c, d: api.run("psf", None, run_dir=d), "run override = None: must be a string"),
    "compose-override-number": (lambda c, d: api.compose(5), "compose override = 5: must be a string 'key=value'"),
    "run-two-overrides-in-one": (lambda c, d: api.run("psf", "debug=smoke mask.levels=8", run_dir=d),
                                 "run override = 'debug=smoke mask.levels=8': holds several overrides: pass each as "
                                 "its own string"),
    "mask_search-path-as-override": (lambda c, d: api.mask_search(str(d)), "mask_search override = "),
    "run-empty-run_dir": (lambda c, d: api.run("psf", "debug=smoke", run_dir=""), "run run_dir = '': must not be "
                          "empty (that is the current directory)"),
    "run-run_dir-number": (lambda c, d: api.run("psf", "debug=smoke", run_dir=123), "run run_dir = 123: must be a "
                           "folder path (str or os.PathLike)"),
    "run-hydra-run-dir": (lambda c, d: api.run("psf", "debug=smoke", "hydra.run.dir=X", run_dir=d),
                          "run override = 'hydra.run.dir=X': the run folder is the run_dir= argument"),
    "run-hydra-sweep": (lambda c, d: api.run("psf", "hydra.sweep.dir=X", run_dir=d),
                        "run override = 'hydra.sweep.dir=X': the run folder is the run_dir= argument"),
    "run-experiment-override": (lambda c, d: api.run("psf", "+experiment=simulate", run_dir=d),
                                "run override = '+experiment=simulate': the experiment is run's own argument"),
    "train_restorer-not-training": (lambda c, d: api.train_restorer("debug=smoke", experiment="psf", run_dir=d),
                                    "train_restorer experiment = 'psf': must be one of baseline, joint"),
    "optical_system-cfg": (lambda c, d: api.optical_system(cfg=5), "optical_system cfg = 5: must be a configuration"),
    "scene_names-cfg": (lambda c, d: api.scene_names(cfg="x"), "scene_names cfg = 'x': must be a configuration"),
    "optical_system-device-tpu": (lambda c, d: api.optical_system(c, device="tpu"), "optical_system device = 'tpu': "
                                  "must be auto, cpu, cuda or cuda:N"),
    "build_camera-device-gpu": (lambda c, d: api.build_camera(c, device="gpu"), "build_camera device = 'gpu': must "
                                "be auto, cpu, cuda or cuda:N"),
    "optical_system-device-cuda3": (lambda c, d: api.optical_system(c, device="cuda:3"),
                                    "optical_system device = 'cuda:3': "),
    "restore_image-device-cuda": (lambda c, d: api.restore_image(np.zeros((96, 96)), device="cuda"),
                                  f"restore_image device = 'cuda': {NO_CUDA}"),
    "configured_mask-system": (lambda c, d: api.configured_mask(c, system="x"), "configured_mask system = 'x': must "
                               "be an OpticalSystem"),
    "published_mask-system": (lambda c, d: api.published_mask(system=5), "published_mask system = 5: must be an "
                              "OpticalSystem"),
    "build_mask-name": (lambda c, d: api.build_mask("nosuch"), "build_mask mask_cfg = 'nosuch': must be a mapping "
                        "of mask.* settings with its 'kind' (build_mask({'kind': FAMILY, ...}, system.grid, "
                        "system.spec.aperture_diameter_m))"),
    "sensor_image-scene-negative": (lambda c, d: api.sensor_image(scene=-1, cfg=c), "sensor_image scene = -1: must "
                                    "be an index 0.."),
    "sensor_image-angle-pair": (lambda c, d: api.sensor_image(cfg=c, laser_angle_rad=[10, 0]),
                                "sensor_image laser_angle_rad[0] = 10: must be a finite number >= -1.5708 and <= "
                                "1.5708"),
    "sensor_image-angle-number": (lambda c, d: api.sensor_image(cfg=c, laser_angle_rad=5),
                                  "sensor_image laser_angle_rad[0] = 5: must be a finite number >= -1.5708"),
    "sensor_image-c2": (lambda c, d: api.sensor_image(cfg=c, c2=1e9), "sensor_image c2 = 1000000000.0: must be a "
                        "finite number >= 0 and <= 10"),
    "restore_image-string": (lambda c, d: api.restore_image("abc"), "restore_image counts = 'abc': must be a 2-D "
                             "array or tensor of sensor counts"),
    "restore_image-none": (lambda c, d: api.restore_image(None), "restore_image counts = None: must be a 2-D array"),
    "restore_image-stack": (lambda c, d: api.restore_image(np.zeros((1000, 96, 96))), "restore_image counts = "
                            "(1000, 96, 96): (C, H, W) takes C <= 16 colour channels"),
    "restore_image-complex": (lambda c, d: api.restore_image(np.zeros((96, 96), complex)), "restore_image counts = "
                              "'<array of complex128>': must be a 2-D array or tensor of sensor counts (H, W), or "
                              "(C, H, W) of real numbers"),
    "restore_image-bool": (lambda c, d: api.restore_image(torch.zeros(96, 96, dtype=torch.bool)),
                           "restore_image counts = '<array of torch.bool>': must be"),
    "quality-strings": (lambda c, d: api.quality("a", "b"), "quality restored = 'a': must be an image (H, W)"),
    "quality-nan": (lambda c, d: api.quality(torch.full((16, 16), float("nan")), torch.zeros(16, 16)),
                    "quality restored = '<array with nan or inf>': must be an image"),
    "quality-scene-negative": (lambda c, d: api.quality(torch.zeros(16, 16), -torch.ones(16, 16)),
                               "quality scene = '<values in [-1, -1]>': must be radiance in [0, 1]"),
    "restore-none": (lambda c, d: api.restore(None, "pretrained", run_dir=d), "restore input = None: must be a "
                     "16-bit PNG/TIFF capture or a folder of them"),
}


@pytest.mark.parametrize("case", list(API_CALLS))
def test_api_refuses_wrong_arguments(cfg, tmp_path, monkeypatch, case):
    call, message = API_CALLS[case]
    if "cuda" in case and torch.cuda.is_available():
        pytest.skip("the machine has CUDA: the device is allowed")
    _experiments_never_run(monkeypatch)
    monkeypatch.chdir(tmp_path)  # an empty run_dir would be this folder: nothing may appear in it
    with pytest.raises(ConfigError) as info:
        call(cfg, tmp_path / "run")
    assert str(info.value).startswith(message), str(info.value)
    assert "\n" not in str(info.value)
    assert not any(tmp_path.iterdir()), "the refused call wrote into the folder"


def test_quality_warns_of_a_restored_image_outside_the_radiance_range():
    scene = torch.rand(16, 16, generator=torch.Generator().manual_seed(0))
    with pytest.warns(UserWarning, match=r"quality restored: values in \[.*\] lie outside \[0, 1\]"):
        out = api.quality(scene * 5, scene)
    assert out["psnr_matched"] > 100  # the matched figures see through the gain


def test_restore_image_warns_of_counts_above_the_sensor_s_full_scale(monkeypatch):
    import codesign.models.capture as capture

    def restored(*args, **kwargs):
        raise WorkStarted
    monkeypatch.setattr(capture, "restore_capture", restored)
    with pytest.warns(UserWarning, match=r"restore_image counts: counts up to 1e\+12 DN exceed the sensor's full "
                      r"scale \d+ DN"), pytest.raises(WorkStarted):
        api.restore_image(np.full((96, 96), 1e12))


class WorkStarted(Exception):
    """The restoration itself began."""


def test_the_command_line_bounds_the_noise_factors_as_the_api():
    # simulate.params.c2=1e9 was simulated too (fixed_scene_params bounded the scene parameters below only)
    from codesign.data.simulate_spec import SimulateSpec

    with pytest.raises(ConfigError, match=re.escape("simulate.params.c2 = 1000000000.0: must be a finite number >= 0 "
                                                    "and <= 10")):
        SimulateSpec.from_config({"params": {"c2": 1e9}})
