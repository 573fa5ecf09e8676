"""Fabrication physics: materials' indices against catalogue values, height <-> phase round trip, the plate's
levels, a 2-level plate's LSR against the closed form and a float64 reference, the plate files' scale."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import yaml

from codesign.design.merit import evaluate_mask
from codesign.errors import ConfigError
from codesign.optics.materials import Material
from codesign.fab.surface import (
    ExportSpec,
    Plate,
    PlatePhase,
    height_of_phase,
    level_index,
    phase_of_height,
    wrap_phase,
)
from codesign.fab.writers import read_height_png, read_height_tiff, write_height_png, write_height_tiff
from codesign.optics import OpticalSystem, OpticsSpec
from tests.conftest import REPO_ROOT


def material(name: str) -> Material:
    return Material.from_config(yaml.safe_load((REPO_ROOT / "conf" / "material" / f"{name}.yaml").read_text()))


@pytest.mark.parametrize("name, wavelength_m, expected", [
    ("fused_silica", 589.3e-9, 1.4585),  # n_d of fused silica (Schott / Corning catalogues)
    ("fused_silica", 632.8e-9, 1.4570),  # HeNe line
    ("pmma", 589.3e-9, 1.4905),  # n_d of PMMA
    ("su8", 633e-9, 1.5867),  # the data sheet's Cauchy fit
])
def test_material_indices_match_catalogue_values(name, wavelength_m, expected):
    assert material(name).index(wavelength_m) == pytest.approx(expected, abs=2e-4)


def test_material_refuses_bad_coefficients():
    with pytest.raises(ConfigError, match=r"material.coefficients\[0\] = \[1.0\]: must be a list of \[B_i, "
                                          r"lambda_i_um\] pairs"):
        Material(formula="sellmeier", coefficients=[[1.0]])
    with pytest.raises(ConfigError, match=r"a mask material needs n > 1"):
        Material(formula="constant", coefficients=[0.9], name="x").index(633e-9)
    with pytest.raises(ConfigError, match=r"material.formula = 'abbe': must be one of sellmeier, cauchy, constant"):
        Material(formula="abbe")


def test_height_phase_round_trip_and_full_wave_depth():
    n, lam = material("fused_silica").index(633e-9), 633e-9
    phase = torch.linspace(-20, 20, 1001, dtype=torch.float64)
    assert torch.allclose(phase_of_height(height_of_phase(phase, lam, n), lam, n), phase, rtol=0, atol=1e-13)
    # height = phase lambda / (2 pi (n - 1)): a 2 pi step in fused silica at 633 nm is 1.3851 um deep
    assert height_of_phase(2 * math.pi, lam, n) == pytest.approx(633e-9 / (n - 1), rel=1e-14)
    assert height_of_phase(2 * math.pi, lam, n) == pytest.approx(1.3851e-6, abs=1e-10)


def test_wrap_and_levels():
    phase = torch.tensor([-2 * math.pi, -0.1, 0.0, 3.0, 2 * math.pi - 1e-12, 7.0], dtype=torch.float64)
    w = wrap_phase(phase)
    assert bool(((w >= 0) & (w < 2 * math.pi)).all())
    assert torch.allclose(torch.exp(1j * w), torch.exp(1j * phase), atol=1e-12)
    # nearest level modulo 2 pi: -0.1 rad and 2 pi - 1e-12 are nearest to level 0 of 4
    assert level_index(w, 4).tolist() == [0, 0, 0, 2, 0, 0]


def _plate_on(system, phase, index, levels):
    return Plate.from_phase(phase, system.grid, system.spec.wavelength_m, index, levels, 1)


def test_plate_seen_on_its_own_grid_is_the_design(small_system64):
    """A continuous plate on the pupil grid itself gives back exp(i phase) to rounding; K levels land on
    multiples of lambda / (K (n - 1)) and never reach the full wave."""
    g = small_system64.grid
    phase = 7.0 * torch.sin(g.u[None, :] / 3e-4) * torch.cos(g.v[:, None] / 5e-4) + 40 * (g.rho / 2e-3) ** 2
    plate = _plate_on(small_system64, phase, 1.5, None)
    back = plate.pupil_phase(g, dtype=torch.float64)
    inside = g.aperture > 0
    assert torch.allclose(torch.exp(1j * back[inside]), torch.exp(1j * phase[inside]), atol=1e-12)
    q = _plate_on(small_system64, phase, 1.5, 8)
    steps = q.height[q.inside] / q.step_m
    assert torch.allclose(steps, torch.round(steps), atol=1e-9)
    assert float(q.height.max()) == pytest.approx(7 / 8 * q.full_wave_depth_m, rel=1e-12)
    assert q.full_wave_depth_m == pytest.approx(633e-9 / 0.5)


def test_two_level_grating_lsr_matches_closed_form_and_float64():
    """A linear phase ramp (period 8 pupil samples) quantized to 2 levels is a binary grating: each first order is
    the aperture's PSF carrying |c_1|^2 of the light, c_1 the first Fourier coefficient of one sampled period;
    its (refined, continuous) peak over the uncoded one is |c_1|^2 = 0.4268. The float32 pipeline matches it and
    the float64 one."""
    spec = OpticsSpec.with_samples_across(128, focal_n=160)
    period = 8
    out = {}
    for dtype in (torch.float32, torch.float64):
        system = OpticalSystem(spec, dtype=dtype)
        g = system.grid
        ramp = 2 * math.pi * (g.u.to(torch.float64) / g.pitch + 0.5) / period  # half a sample off the level ties
        plate = _plate_on(system, ramp[None, :].expand(g.n, g.n), 1.4570, 2)
        values, _ = evaluate_mask(system, PlatePhase(plate.pupil_phase(g, dtype=dtype)), (0.0, 0.5), 16.0)
        out[dtype] = values["lsr"]
    levels = np.round(np.mod(2 * np.pi * (np.arange(period) + 0.5) / period, 2 * np.pi) / np.pi) % 2
    c1 = np.fft.fft(np.exp(1j * np.pi * levels))[1] / period
    assert levels.tolist() == [0, 0, 1, 1, 1, 1, 0, 0]
    assert abs(c1) ** 2 == pytest.approx(0.4268, abs=1e-4)
    assert out[torch.float64] == pytest.approx(abs(c1) ** 2, rel=5e-3)  # other orders' tails: < 0.5 %
    assert out[torch.float32] == pytest.approx(out[torch.float64], rel=1e-4)


def test_export_spec_refuses_a_plate_smaller_than_the_aperture():
    spec = OpticsSpec()
    with pytest.raises(ConfigError, match=r"export.size_m = 0.003: .*must hold the aperture's support"):
        ExportSpec(size_m=3e-3).plate_n(spec)
    with pytest.raises(ConfigError, match=r"export.pitch_m = 1e-07: .*at most 8192 per side"):
        ExportSpec(pitch_m=1e-7).plate_n(spec)
    with pytest.raises(ConfigError, match=r"export.levels = 1: .*>= 2 and <= 256"):
        ExportSpec(levels=1)
    assert ExportSpec(pitch_m=2e-6).plate_n(spec) == 1992


def test_height_files_hold_their_scale(tmp_path):
    rng = np.random.default_rng(0)
    full = 1.3853e-6
    height = rng.uniform(0, full, (40, 30))
    meta = {"metres_per_count": full / 65535, "pitch_m": 2e-6}
    write_height_png(tmp_path / "h.png", height, full / 65535, meta)
    write_height_tiff(tmp_path / "h.tif", height, full / 65535, 2e-6, meta)
    back, scale, m = read_height_png(tmp_path / "h.png")
    assert scale == full / 65535 and m == meta
    assert np.abs(back - height).max() <= 0.5 * scale * (1 + 1e-9)
    back_t, m_t = read_height_tiff(tmp_path / "h.tif")
    assert m_t == meta and np.array_equal(back_t, back)
    import tifffile

    with tifffile.TiffFile(tmp_path / "h.tif") as tif:
        page = tif.pages[0]
        assert page.dtype == np.uint16
        assert page.tags["XResolution"].value[0] / page.tags["XResolution"].value[1] == pytest.approx(5000.0)


@pytest.mark.parametrize("wrap", [None, 1, 3])
def test_plate_wrap_depths_and_the_same_design(small_system64, wrap):
    """Wrapped at 2 pi m the heights lie in [0, m lambda / (n - 1)); a continuous surface keeps the phase's whole
    relief, its lowest point at 0. At the design wavelength all three give the design's field back (to a piston:
    the continuous surface starts from its lowest point)."""
    g = small_system64.grid
    phase = 60 * (g.rho / 2e-3) ** 2 - 9.0
    plate = Plate.from_phase(phase, g, 633e-9, 1.5, None, wrap)
    h = plate.height[plate.inside]
    relief = float(phase[plate.inside].max() - phase[plate.inside].min()) * 633e-9 / (2 * math.pi * 0.5)
    if wrap is None:
        assert float(h.min()) == pytest.approx(0.0, abs=1e-18)
        assert float(h.max()) == pytest.approx(relief, rel=1e-12)
        assert plate.depth_m == pytest.approx(relief, rel=1e-12)
    else:
        assert float(h.min()) >= 0 and float(h.max()) < wrap * plate.full_wave_depth_m
        assert plate.depth_m == pytest.approx(wrap * 633e-9 / 0.5, rel=1e-14)
    inside = g.aperture > 0
    d = torch.exp(1j * (plate.pupil_phase(g, dtype=torch.float64) - phase)[inside])
    assert torch.allclose(d, d[:1].expand_as(d), atol=1e-11)


def test_multi_order_levels_span_the_wrap(small_system64):
    g = small_system64.grid
    q = Plate.from_phase(60 * (g.rho / 2e-3) ** 2, g, 633e-9, 1.5, 8, 2)
    assert q.step_m == pytest.approx(2 * 633e-9 / 0.5 / 8, rel=1e-14)  # 8 levels over two waves
    steps = q.height[q.inside] / q.step_m
    assert torch.allclose(steps, torch.round(steps), atol=1e-9) and float(steps.max()) <= 7 + 1e-9
    with pytest.raises(ValueError, match="a continuous surface"):
        Plate.from_phase(60 * (g.rho / 2e-3) ** 2, g, 633e-9, 1.5, 8, None)
