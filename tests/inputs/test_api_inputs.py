"""The Python API (codesign/api.py) checks its arguments as the command line checks its keys: a wrong one is a
ConfigError naming the function and the argument, the value and what is allowed, raised before any work (it was
accepted, or an AttributeError / RuntimeError from deep inside)."""
from __future__ import annotations

import re

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
