"""model.g1_halo: G1's fourth channel, the system PSF spread over the saturated pixels (codesign/models/sgan.py
halo_map), checked against its closed form for one saturated pixel, and G1's use of it."""
from __future__ import annotations

import math

import pytest
import torch

from codesign.errors import ConfigError
from codesign.models import SGAN, ModelSpec, otf_from_kernel
from codesign.models.sandwich import HALO_DECADES, halo_map

P = 32


def _kernel() -> torch.Tensor:
    """A PSF kernel at the origin (wrapped): a core and a ring of wings 1e-1 .. 1e-8 of it, the last below the
    channel's floor."""
    k = torch.zeros(P, P, dtype=torch.float64)
    k[0, 0] = 1.0
    for d, v in ((1, 1e-1), (2, 1e-3), (3, 1e-5), (5, 1e-8)):
        k[d, 0] = k[-d, 0] = k[0, d] = k[0, -d] = v
    return k


def _level(rel: float) -> float:
    return min(max(1 + math.log10(rel) / HALO_DECADES, 0.0), 1.0) if rel > 0 else 0.0


def test_one_saturated_pixel_gives_the_psf_in_decades():
    k = _kernel()
    otf = torch.fft.rfft2(k)
    sensor = torch.full((1, 1, P, P), 0.5)
    y0, x0 = 11, 17
    sensor[0, 0, y0, x0] = 1.0
    h = halo_map(sensor, otf)[0, 0].double()
    expect = torch.tensor([[_level(float(k[(y - y0) % P, (x - x0) % P])) for x in range(P)] for y in range(P)],
                          dtype=torch.float64)
    assert torch.allclose(h, expect, atol=1e-6)
    assert float(h[y0, x0]) == 1.0 and float(h[y0 + 3, x0]) == pytest.approx(1 - 5 / HALO_DECADES, abs=1e-6)
    assert float(h[y0 + 5, x0]) == 0.0  # 1e-8 of the peak: below the floor


def test_no_saturated_pixel_gives_zero_and_the_channel_is_shift_equivariant():
    otf = torch.fft.rfft2(_kernel())
    sensor = torch.rand(2, 1, P, P, generator=torch.Generator().manual_seed(0)) * 0.9
    assert torch.equal(halo_map(sensor, otf)[0], torch.zeros(1, P, P))
    sensor[1, 0, 4:7, 20:24] = 1.0
    shifted = torch.roll(sensor, (5, -3), dims=(-2, -1))
    assert torch.allclose(halo_map(shifted, otf), torch.roll(halo_map(sensor, otf), (5, -3), dims=(-2, -1)),
                          atol=1e-6)


def test_g1_sees_the_halo_channel_and_so_the_mask():
    torch.manual_seed(0)
    spec = ModelSpec(size="tiny", fe_features=4, g1_halo=True)
    model = SGAN(spec)
    assert model.g1.head[0][0].in_channels == 4
    sensor = torch.rand(1, 1, 64, 64) * 0.5
    sensor[..., 30:33, 30:33] = 1.0
    narrow, wide = torch.zeros(5, 5), torch.ones(5, 5)
    narrow[2, 2] = 1.0
    # G1's output layer starts at zero: give it weights so that its input reaches I_b^
    torch.nn.init.normal_(model.g1.body.out.weight, std=0.1)
    with torch.no_grad():
        a = model(sensor, otf_from_kernel(narrow, 64))["i_b"]
        b = model(sensor, otf_from_kernel(wide / wide.sum(), 64))["i_b"]
    assert (a - b).abs().max() > 1e-4  # the same sensor image, two masks: two pre-restorations
    plain = SGAN(ModelSpec(size="tiny", fe_features=4))
    assert plain.g1.head[0][0].in_channels == 3


def test_g1_halo_must_be_a_boolean():
    with pytest.raises(ConfigError) as err:
        ModelSpec(g1_halo="yes")
    assert str(err.value) == "model.g1_halo = 'yes': must be true or false"
