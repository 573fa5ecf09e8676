"""Restorability: the sensor's noise variance against simulated images, the Wiener MSE formula against a Monte
Carlo of Gaussian scenes with the fitted spectrum, its response to blur, noise and the laser, and its gradient."""
from __future__ import annotations

import math

import pytest
import torch
from hydra import compose, initialize_config_dir

from codesign.camera import build_camera
from codesign.data.params import fixed_scene_params
from codesign.design.restorability import (Restorability, SceneSpectrum, fit_scene_spectrum, noise_variance,
                                           restorability_for)
from tests.conftest import REPO_ROOT

SMOKE = ["optics.pupil_pitch_m=2.0e-5", "optics.focal_n=160", "data.image_size=64", "data.padded_size=96"]


@pytest.fixture(scope="module")
def camera():
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["+experiment=baseline", *SMOKE])
    return build_camera(cfg, "cpu")


def test_noise_variance_matches_simulated_flat_scenes(camera):
    """A uniform scene b = 0.5 at the figure settings: the variance of the normalized sensor pixels is sigma^2."""
    n_scene = camera.scene_size
    scenes = torch.full((4, 1, n_scene, n_scene), 0.5)
    params = fixed_scene_params(4, alpha_l=0.0)
    out = camera(scenes, params, seed=3)
    m = (camera.padded_size - camera.image_size) // 2
    field = out["sensor"][..., m:m + camera.image_size, m:m + camera.image_size].to(torch.float64)
    measured = float(field.var(dim=(-2, -1)).mean())
    assert measured == pytest.approx(noise_variance(camera.sensor, None, 0.5), rel=0.05)  # 4 x 64^2 samples


def test_wiener_mse_matches_a_monte_carlo_of_gaussian_scenes():
    """Gaussian scenes with spectrum S, blurred by a known kernel, white noise N: the exact Wiener filter's mean
    squared error (mean removed) equals Restorability.mse."""
    n, a, noise = 64, 0.6, 2e-4
    spectrum = SceneSpectrum(2e-4, 2.2)
    kernel = torch.tensor([[0.05, 0.1, 0.05], [0.1, 0.4, 0.1], [0.05, 0.1, 0.05]], dtype=torch.float64)
    module = Restorability(n, spectrum, noise, alpha_b=a, edge=False)  # circular scenes: no field edge
    s, h2 = module.s, module.otf(kernel)
    pad = torch.zeros(n, n, dtype=torch.float64)
    pad[:3, :3] = kernel
    h = torch.fft.fft2(torch.roll(pad, (-1, -1), (0, 1)))
    gen = torch.Generator().manual_seed(0)
    errs = []
    for _ in range(200):
        coef = torch.complex(torch.randn(n, n, generator=gen, dtype=torch.float64),
                             torch.randn(n, n, generator=gen, dtype=torch.float64)) * (s / 2).sqrt()
        b = torch.fft.ifft2(coef, norm="ortho").real * math.sqrt(2)  # real part of a complex field: spectrum S
        y = torch.fft.ifft2(torch.fft.fft2(b) * h).real * a + math.sqrt(noise) * torch.randn(n, n, generator=gen,
                                                                                           dtype=torch.float64)
        y_f = torch.fft.fft2(y, norm="ortho")
        n_scene = noise / a**2
        b_hat = torch.fft.ifft2(y_f / a * h.conj() * s / (h2 * s + n_scene), norm="ortho").real
        d = b_hat - b
        errs.append(float(((d - d.mean()) ** 2).mean()))
    mc = sum(errs) / len(errs)
    assert mc == pytest.approx(float(module.mse(kernel)), rel=0.05)  # 200 samples: ~2 % noise


def test_more_blur_or_noise_lowers_it_and_the_laser_costs_the_saturated_area():
    spectrum = SceneSpectrum(2e-4, 2.2)
    sharp = torch.zeros(5, 5, dtype=torch.float64)
    sharp[2, 2] = 1.0
    blur = torch.full((5, 5), 1 / 25, dtype=torch.float64)
    quiet, loud = Restorability(64, spectrum, 1e-5), Restorability(64, spectrum, 1e-3)
    assert float(quiet(sharp)) > float(quiet(blur)) and float(quiet(sharp)) > float(loud(sharp))
    laser = Restorability(64, spectrum, 1e-5, alpha_l=1e4, uncoded_peak=1.0, bins=1.0)
    assert float(laser.lost_fraction(sharp)) == pytest.approx(1 / 64**2, rel=1e-3)  # one pixel at 1e4 I_sat
    assert float(laser.lost_fraction(blur)) == pytest.approx(25 / 64**2, rel=1e-3)  # 25 pixels at 400 I_sat
    assert float(laser(blur)) < float(quiet(blur))


def test_noise_variance_of_a_textured_scene_uses_its_mean_square():
    """Half the scene at 0.2, half at 0.8 (uncoded aperture: the halves stay apart): the photo-response term
    follows the mean of the signal's square, not the square of its mean. The variance of two captures'
    difference / 2 is the noise alone."""
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["+experiment=baseline", *SMOKE, "mask=zernike", "mask.init=zero"])
    camera = build_camera(cfg, "cpu")
    n_scene = camera.scene_size
    scenes = torch.full((4, 1, n_scene, n_scene), 0.2)
    scenes[..., n_scene // 2:] = 0.8
    params = fixed_scene_params(4, alpha_l=0.0)
    m, n = (camera.padded_size - camera.image_size) // 2, camera.image_size
    first, second = camera(scenes, params, seed=3), camera(scenes, params, seed=4)
    diff = (first["sensor"] - second["sensor"]).to(torch.float64)[..., m:m + n, m:m + n]
    signal = first["irradiance"].to(torch.float64)[..., m:m + n, m:m + n] / float(params.alpha_b[0])
    mean, square = float(signal.mean()), float(signal.square().mean())
    assert float(diff.var()) / 2 == pytest.approx(noise_variance(camera.sensor, None, mean, square), rel=0.05)
    assert noise_variance(camera.sensor, None, mean, square) > 1.2 * noise_variance(camera.sensor, None, mean)


def test_edge_fraction_is_the_light_each_field_pixel_receives_from_beyond_the_field():
    """By hand: half the light on axis, half 4 pixels to the right: a pixel in the 4 columns nearest the right
    border gets that half from outside, L = 0.5 x 4 / 64. And for any kernel, the mean over the field of
    (light from all pixels - light from field pixels), computed by convolving the field's indicator."""
    module = Restorability(64, SceneSpectrum(2e-4, 2.2), 1e-5)
    two = torch.zeros(9, 9, dtype=torch.float64)
    two[4, 4] = two[4, 8] = 0.5
    assert float(module.edge_fraction(two)) == pytest.approx(0.5 * 4 / 64, rel=1e-12)
    delta = torch.zeros(9, 9, dtype=torch.float64)
    delta[4, 4] = 1.0
    assert float(module.edge_fraction(delta)) == 0.0
    kernel = torch.rand(21, 21, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    kernel /= kernel.sum()
    field = torch.nn.functional.pad(torch.ones(1, 1, 64, 64, dtype=torch.float64), (10,) * 4)
    from_field = torch.nn.functional.conv2d(field, kernel.flip(-1, -2)[None, None])[0, 0]
    assert float(module.edge_fraction(kernel)) == pytest.approx(float((1 - from_field).mean()), rel=1e-12)
    # the lost share costs the scene's variance: a wide kernel scores below the same kernel on an infinite field
    circular = Restorability(64, SceneSpectrum(2e-4, 2.2), 1e-5, edge=False)
    assert float(module(kernel)) < float(circular(kernel))


def test_fitted_spectrum_of_natural_scenes_falls_like_a_power_law(camera):
    from codesign.data.scenes import build_scene_source

    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["+experiment=baseline", *SMOKE])
    source = build_scene_source(cfg.data)
    spec = fit_scene_spectrum(source.fixed_batch(source.split_names("train"), 128))
    assert 1.5 < spec.exponent < 3.5 and spec.amplitude > 0  # natural images: ~1/f^2 (measured 2.57 at 128 px)


def test_it_is_differentiable_in_the_mask_parameters(camera):
    """d PSNR / d (spiral coefficients) by autograd through PSF, kernel and Restorability matches finite
    differences (float64 kernel path; the float32 PSF's rounding sets the tolerance)."""
    from codesign.optics.masks import build_mask

    system = camera.system
    mask = build_mask({"kind": "spiral", "charge": 1.5, "axicon_cycles": 2.0, "defocus_rad": 5.0}, system.grid,
                      system.spec.aperture_diameter_m)
    module = restorability_for(camera, spectrum=SceneSpectrum(2e-4, 2.2))

    def psnr(x):
        mask.set_vector(x)
        return module(camera.optics_of(mask.phase()).kernel)

    x = mask.to_vector()
    psnr(x).backward()
    grad = mask.vector_grad()
    for i, h in enumerate((1e-2, 1e-2, 1e-2)):
        e = torch.zeros_like(x)
        e[i] = h
        with torch.no_grad():
            fd = (float(psnr(x + e)) - float(psnr(x - e))) / (2 * h)
        assert float(grad[i]) == pytest.approx(fd, rel=0.05, abs=1e-3), i
