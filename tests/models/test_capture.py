"""Restoring a capture of any size (codesign/models/capture.py): exact area binning, the canvas that holds the PSF
kernel, the OTF at the network pixel, and a fresh conditioned network passing a uniform scene through at its level."""
from __future__ import annotations

import pytest
import torch

from codesign.errors import ConfigError
from codesign.models.capture import (RestoreSpec, bin_counts, binned_shape, capture_geometry, network_bin,
                                     restore_capture)
from codesign.models.wiener_naf import WienerNAF, WienerNAFSpec
from codesign.models.wiener_unet import WienerUNet
from codesign.sensor.spec import SensorSpec, kernel_size

DX = 5.4e-6
EXTENT = 640 * DX  # the default optics window


def test_binning_is_an_exact_area_average_for_any_factor():
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(50, 35, generator=gen, dtype=torch.float64) * 1000
    for factor in (1.0, 2.0, 2.5, 3.7):
        out = bin_counts(x, factor, 65535.0)
        h, w = binned_shape((50, 35), factor)
        assert out.shape == (h, w) == (int(50 // factor), int(35 // factor))
        # each output pixel: the integral of the piecewise-constant input over its f x f square, over f^2
        y, z = 1, 2
        r0, r1, c0, c1 = y * factor, (y + 1) * factor, z * factor, (z + 1) * factor
        i, j = torch.arange(51, dtype=torch.float64), torch.arange(36, dtype=torch.float64)
        rows = (torch.clamp(i[1:], max=r1) - torch.clamp(i[:-1], min=r0)).clamp_min(0)
        cols = (torch.clamp(j[1:], max=c1) - torch.clamp(j[:-1], min=c0)).clamp_min(0)
        want = float((rows[:, None] * cols[None, :] * x).sum() / factor**2)
        assert abs(float(out[y, z]) - want) < 1e-9 * want
    assert torch.allclose(bin_counts(torch.full((30, 20), 7.0, dtype=torch.float64), 2.9, 100.0),
                          torch.full((10, 6), 7.0, dtype=torch.float64))


def test_a_bin_touching_a_saturated_pixel_reads_full_scale():
    x = torch.full((20, 20), 100.0, dtype=torch.float64)
    x[9, 9] = 9435.0  # one clipped sensor pixel
    out = bin_counts(x, 4.0, 9435.0)
    assert float(out[2, 2]) == 9435.0
    assert int((out == 9435.0).sum()) == 1 and float(out[0, 0]) == 100.0


def test_the_canvas_holds_the_kernel_and_centres_the_image():
    g = capture_geometry((2532, 1900), 2532 / 256, DX, EXTENT)
    assert g.size == (256, 192) and g.kernel == kernel_size(EXTENT, DX * 2532 / 256) == 65
    assert all(c >= n + g.kernel - 1 and c % 8 == 0 for c, n in zip(g.canvas, g.size))
    assert g.offset == ((g.canvas[0] - 256) // 2, (g.canvas[1] - 192) // 2)
    full = capture_geometry((1080, 1920), 1.0, DX, EXTENT)
    assert full.size == (1080, 1920) and full.kernel == 641


def test_the_network_scale_is_the_finest_trained_one():
    assert network_bin({"sensor": {"resolution": 2532}, "data": {"image_size": 96, "scales": [96, 256]}}) == 2532 / 256
    assert network_bin({"sensor": {"resolution": 2532}, "data": {"image_size": 96}}) == 2532 / 96
    assert RestoreSpec().tile_for(capture_geometry((2532, 2532), 1.0, DX, EXTENT)) == 512
    assert RestoreSpec().tile_for(capture_geometry((2532, 2532), 9.89, DX, EXTENT)) is None
    with pytest.raises(ConfigError, match=r"^restore\.bin = 0\.5: "):
        RestoreSpec(bin=0.5)


def _point_psf(m: int = 41) -> torch.Tensor:
    psf = torch.zeros(m, m)
    psf[m // 2 - 2: m // 2 + 3, m // 2 - 2: m // 2 + 3] = 1 / 25
    return psf


def test_a_fresh_network_restores_a_uniform_capture_of_any_shape_at_its_level():
    sensor = SensorSpec()
    full_well_dn = sensor.gain_dn_per_e * sensor.full_well_e
    counts = torch.full((300, 180), 0.4 * full_well_dn, dtype=torch.float64)
    model = WienerNAF(WienerNAFSpec(size="tiny"))
    g = capture_geometry(tuple(counts.shape), 2.5, DX, 41 * DX)
    out = restore_capture(model, counts, _point_psf(), sensor, g)
    assert out.shape == (1, 120, 72)
    assert float((out - 0.4).abs().max()) < 1e-4  # unit DC gain through the bank, the fill continues the border
    tiled = restore_capture(model, counts, _point_psf(), sensor, g, tile=32)
    assert float((tiled - out).abs().max()) < 1e-5


def test_a_fixed_size_network_is_refused_for_any_size():
    g = capture_geometry((64, 64), 1.0, DX, 41 * DX)
    with pytest.raises(ConfigError, match=r"^checkpoint = 'wiener_unet': restores captures of its training size "
                       r"only; a capture of any size needs a network that takes any size \(model=wiener_naf"):
        restore_capture(WienerUNet(), torch.zeros(64, 64), _point_psf(), SensorSpec(), g)
