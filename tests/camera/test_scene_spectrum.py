"""The scene over a band (optics.scene_spectrum): its PSF the weighted mean of the mask's PSFs at the band's
wavelengths, the laser at its own line, and the settings refused before any work."""
from __future__ import annotations

import pytest
import torch

from codesign.camera.build import build_camera
from codesign.camera.camera import spectral_state
from codesign.errors import ConfigError
from codesign.optics import OpticsSpec
from codesign.sensor.simulator import psf_state
from tests.inputs._run import compose_cfg
from tests.sensor.test_laser_halo import SMALL

BAND = "optics.scene_spectrum=[[5.0e-7,1.0],[6.33e-7,3.0]]"


def _camera(*overrides):
    return build_camera(compose_cfg("+experiment=simulate", *SMALL, "sensor.laser_halo=false", *overrides),
                        torch.device("cpu"), torch.float64)


def test_one_sample_at_the_design_wavelength_is_the_monochromatic_camera():
    mono, band = _camera(), _camera("optics.scene_spectrum=[[6.33e-7,2.5]]")
    a, b = mono.frozen_optics().state, band.frozen_optics().state
    torch.testing.assert_close(b.psf, a.psf, rtol=1e-15, atol=0)
    assert b.uncoded_peak == pytest.approx(a.uncoded_peak, rel=1e-15)
    assert b.laser is not None and torch.equal(b.laser.psf, a.psf)  # the laser: the design line's own PSF


def test_band_psf_is_the_weighted_mean_and_the_laser_keeps_its_line():
    camera = _camera(BAND)
    state = camera.frozen_optics().state
    lines, weights = camera.scene_spectrum
    assert lines.wavelengths == (5.0e-7, 6.33e-7) and weights == (1.0, 3.0)
    with torch.no_grad():
        phase = camera.mask.phase()
        parts = [psf_state(s, lines.phase(phase, i)) for i, s in enumerate(lines.systems)]
    torch.testing.assert_close(state.psf, (parts[0].psf + 3 * parts[1].psf) / 4, rtol=1e-12, atol=0)
    # the window's energy and the uncoded normalizers are the band's weighted means too
    assert float(state.psf.sum()) == pytest.approx((float(parts[0].psf.sum()) + 3 * float(parts[1].psf.sum())) / 4,
                                                   rel=1e-12)
    assert state.uncoded_peak == pytest.approx((parts[0].uncoded_peak + 3 * parts[1].uncoded_peak) / 4, rel=1e-15)
    assert not torch.allclose(state.psf, parts[1].psf)  # 500 nm changes the scene's PSF
    torch.testing.assert_close(state.laser.psf, parts[1].psf, rtol=0, atol=0)  # the laser: 633 nm alone
    assert state.laser.uncoded_peak == parts[1].uncoded_peak
    torch.testing.assert_close(spectral_state(lines, weights, phase, None).psf, state.psf, rtol=0, atol=0)


def test_spectrum_settings_are_checked():
    with pytest.raises(ConfigError, match=r"optics.scene_spectrum\[0\] = \[5e-07\]: must be null \(the design "
                                          r"wavelength alone\) or a list of \[wavelength_m, weight\] pairs"):
        OpticsSpec(scene_spectrum=[[5e-7]])
    with pytest.raises(ConfigError, match=r"optics.scene_spectrum\[1\]\[1\] = 0: must be a finite number > 0 "
                                          r"and <= 1e\+12"):
        OpticsSpec(scene_spectrum=[[5e-7, 1.0], [6e-7, 0]])
    with pytest.raises(ConfigError, match=r"optics.scene_spectrum\[0\]\[0\] = 4e-07: at this wavelength the sampled "
                                          r"pupil's spectrum repeats every"):
        OpticsSpec(focal_n=1280, scene_spectrum=[[4e-7, 1.0]])
    with pytest.raises(ConfigError, match="names a wavelength twice"):
        OpticsSpec(scene_spectrum=[[5e-7, 1.0], [5e-7, 2.0]])
