"""A laser at another line than the scene (sensor.wavelength_laser_m): its own PSF, the mask's surface seen at that
wavelength, in the laser term alone; the scene's term stays the design wavelength's."""
from __future__ import annotations

import pytest
import torch
from codesign.camera import build_camera
from codesign.errors import ConfigError
from codesign.optics import OpticalSystem, OpticsSpec
from codesign.optics.lines import LaserLines
from codesign.optics.masks import published_halfring
from codesign.optics.materials import Material
from codesign.sensor.simulator import SensorSimulator, psf_state
from codesign.sensor.spec import SensorSpec
from tests.inputs._run import compose_cfg
from tests.sensor.test_laser_halo import SMALL
from . import _util as U

LINE = 450e-9


def _setup():
    spec = OpticsSpec.with_samples_across(48, focal_n=U.ODD, laser_wavelengths_m=[LINE, 633e-9])
    system = OpticalSystem(spec, dtype=torch.float64)
    phase = published_halfring(system.grid, spec.aperture_diameter_m).phase().detach()
    lines = LaserLines(system, Material().index, (LINE,))
    state = psf_state(system, phase)
    state.laser = psf_state(lines.systems[0], lines.phase(phase, 0))
    sensor = SensorSpec(resolution=33, image_size=33, padded_size=33, background_veil=False, pixel_integration=False,
                        wavelength_laser_m=LINE)
    return SensorSimulator(sensor, spec), state, psf_state(system, phase)


def test_laser_term_is_the_lines_psf_and_the_scene_the_designs():
    sim, state, design = _setup()
    alpha = 1e4
    scene = U.random_scene(sim)
    out = sim(scene, U.params(alpha_l=alpha), state, seed=0)
    line = state.laser
    expect = alpha * line.psf.clamp_min(0) / line.uncoded_peak
    torch.testing.assert_close(out["laser"][0, 0], expect, rtol=1e-9, atol=1e-9 * float(expect.max()))
    # the published plate at 450 nm: LSR 3.6e-3 against 8.6e-3 at its design line (docs/optics.md): another peak
    assert float(line.psf.max()) / line.uncoded_peak != pytest.approx(float(design.psf.max()) / design.uncoded_peak,
                                                                      rel=0.05)
    no_laser = sim(scene, U.params(alpha_l=0.0), state, seed=0)
    same = sim(scene, U.params(alpha_l=0.0), design, seed=0)
    torch.testing.assert_close(no_laser["irradiance"], same["irradiance"], rtol=0, atol=0)


def test_laser_line_must_be_a_configured_line():
    spec = OpticsSpec.with_samples_across(48, focal_n=U.ODD)
    sensor = SensorSpec(resolution=33, image_size=33, padded_size=33, wavelength_laser_m=LINE)
    with pytest.raises(ConfigError) as err:
        SensorSimulator(sensor, spec)
    assert str(err.value) == ("sensor.wavelength_laser_m = 4.5e-07: must be the design wavelength (6.33e-07) or one "
                              "of optics.laser_wavelengths_m (null): the laser's PSF is computed at those lines (add "
                              "the line to optics.laser_wavelengths_m)")


def test_camera_builds_the_lines_state_and_halo():
    """The camera's laser state is the line's PSF of the mask's surface, with the halo of the line's far PSF."""
    camera = build_camera(compose_cfg("+experiment=simulate", *SMALL, "optics.laser_wavelengths_m=[4.5e-7,6.33e-7]",
                                      "sensor.wavelength_laser_m=4.5e-7"), torch.device("cpu"))
    state = camera.frozen_optics().state
    lines = camera.laser_line
    assert lines is not None and lines.wavelengths == (LINE,)
    with torch.no_grad():
        expect = lines.systems[0].psf(lines.phase(camera.mask.phase(), 0))
    torch.testing.assert_close(state.laser.psf, expect, rtol=0, atol=0)
    assert state.laser.uncoded_peak == lines.systems[0].uncoded_peak
    line_halo, design_halo = state.laser.halo(), state.halo()
    assert line_halo is not design_halo
    assert not torch.equal(line_halo.integral, design_halo.integral)  # another wavelength, another far PSF
    assert build_camera(compose_cfg("+experiment=simulate", *SMALL), torch.device("cpu")).laser_line is None


def test_checkpoints_written_before_the_lines_resume_and_warm_start(tmp_path):
    """A checkpoint's configuration without the laser-line keys (every checkpoint written before them) reads as the
    design wavelength alone, the 2 pi plate, fused silica and the design line's constraint: the values it was trained
    with, so resuming it under today's defaults passes and under another material does not."""
    from omegaconf import OmegaConf

    from codesign.config.runtime import to_container
    from codesign.experiments.resume import check_resume_config

    cfg = compose_cfg("+experiment=joint", "debug=smoke")
    old = to_container(cfg)
    for key in ("laser_wavelengths_m", "wrap_waves", "scene_spectrum"):
        old["optics"].pop(key)
    old.pop("material")
    old["codesign"].pop("lsr_over")
    check_resume_config(old, cfg, "trainer.resume", ("codesign",))
    other = compose_cfg("+experiment=joint", "debug=smoke", "material=pmma")
    with pytest.raises(ConfigError, match="was trained with different material"):
        check_resume_config(old, other, "trainer.resume", ("codesign",))
    assert OmegaConf.select(cfg, "codesign.lsr_over") == "design"
