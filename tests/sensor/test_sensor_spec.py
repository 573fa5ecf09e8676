"""SensorSpec: derived quantities (Table 1) and validation errors that name the offending key."""
from __future__ import annotations


import pytest

from codesign.errors import ConfigError
from codesign.sensor.spec import LIGHT_M_S, PLANCK_J_S, SensorSpec, kernel_size


def test_table1_defaults_and_derived_values():
    s = SensorSpec()
    assert s.saturation_dn == 65535.0
    assert s.bin_factor == pytest.approx(2532 / 256)
    assert s.coarse_pitch_m == pytest.approx(5.4e-6 * 2532 / 256)
    # I_sat = e_sat h c / (lambda t dx^2 Q_e)
    i_sat = 25500 * PLANCK_J_S * LIGHT_M_S / (633e-9 * 0.1 * (5.4e-6) ** 2 * 0.56)
    assert s.saturation_irradiance(633e-9) == pytest.approx(i_sat, rel=1e-12)
    assert s.saturation_irradiance(633e-9, exposure_s=0.2) == pytest.approx(i_sat / 2, rel=1e-12)
    # the photons of I_sat over one pixel and exposure, times Q_e, fill the well
    photons = s.saturation_irradiance(633e-9) * 0.1 * (5.4e-6) ** 2 * s.photons_per_joule(633e-9)
    assert photons * s.quantum_efficiency == pytest.approx(s.full_well_e, rel=1e-12)


@pytest.mark.parametrize("extent,pitch,expect", [(32 * 5.4e-6, 5.4e-6, 33), (33 * 5.4e-6, 5.4e-6, 33),
                                                 (32 * 5.4e-6, 4 * 5.4e-6, 9), (33 * 5.4e-6, 3 * 5.4e-6, 11),
                                                 (640 * 5.4e-6, 2532 / 256 * 5.4e-6, 65)])
def test_kernel_size_is_odd_and_covers_the_extent(extent, pitch, expect):
    k = kernel_size(extent, pitch)
    assert k == expect and k % 2 == 1 and k * pitch >= extent * (1 - 1e-12)


@pytest.mark.parametrize("kwargs,key", [
    (dict(full_well_e=-1), "sensor.full_well_e"),
    (dict(full_well_e=0), "sensor.full_well_e"),
    (dict(gain_dn_per_e=0.0), "sensor.gain_dn_per_e"),
    (dict(quantum_efficiency=1.5), "sensor.quantum_efficiency"),
    (dict(quantum_efficiency=0.0), "sensor.quantum_efficiency"),
    (dict(exposure_s=0.0), "sensor.exposure_s"),
    (dict(read_noise_std_e=-0.1), "sensor.read_noise_std_e"),
    (dict(read_noise_mean_e=float("nan")), "sensor.read_noise_mean_e"),
    (dict(dark_current_mean_e=-1e-3), "sensor.dark_current_mean_e"),
    (dict(wavelength_laser_m=633.0), "sensor.wavelength_laser_m"),
    (dict(pixel_pitch_m=0.0), "sensor.pixel_pitch_m"),
    (dict(bit_depth=0), "sensor.bit_depth"),
    (dict(bit_depth=12.5), "sensor.bit_depth"),
    (dict(resolution=4), "sensor.resolution"),
    (dict(image_size=300, padded_size=256), "sensor.padded_size"),
    (dict(resolution=200, image_size=256), "sensor.resolution"),
    (dict(image_size=256.5), "sensor.image_size"),
    (dict(path="foo"), "sensor.path"),
    (dict(downsample="nearest"), "sensor.downsample"),
    (dict(pixel_integration="yes"), "sensor.pixel_integration"),
    (dict(pixel_integration=1), "sensor.pixel_integration"),
])
def test_bad_values_raise_config_error_naming_the_key(kwargs, key):
    with pytest.raises(ConfigError) as info:
        SensorSpec(**kwargs)
    assert info.value.key == key
    assert str(info.value).startswith(key)


def test_from_config_rejects_unknown_keys_and_uses_the_prefix():
    with pytest.raises(ConfigError) as info:
        SensorSpec.from_config({"resolution": 64, "image_sise": 16})
    assert info.value.key == "sensor.image_sise"
    assert "allowed" in str(info.value)
    with pytest.raises(ConfigError) as info:
        SensorSpec.from_config({"path": "bar"}, prefix="data.sensor")
    assert info.value.key == "data.sensor.path"
    s = SensorSpec.from_config({"resolution": 64.0, "image_size": 16, "padded_size": 20, "path": "full"})
    assert s.resolution == 64 and isinstance(s.resolution, int) and s.path == "full"


def test_replace_validates():
    s = SensorSpec(resolution=64, image_size=16, padded_size=16)
    assert s.replace(path="full").path == "full"
    with pytest.raises(ConfigError, match="sensor.padded_size"):
        s.replace(padded_size=8)
