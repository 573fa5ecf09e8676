"""The laser lines in the experiments: optics.laser_wavelengths_m reported by psf (per-line table, LSR against
wavelength), searched over by mask_search (search.lsr_over=wavelengths), and the settings refused before any work."""
from __future__ import annotations

import json

import pytest

from tests.cli import run_codesign
from tests.inputs._run import config_error

LINES = "optics.laser_wavelengths_m=[4.5e-7,5.32e-7,6.33e-7]"


@pytest.mark.parametrize("overrides, message", [
    (("+experiment=mask_search", "search.lsr_over=wavelengths"),
     "search.lsr_over = 'wavelengths': takes the worst LSR over the laser lines, and optics.laser_wavelengths_m is "
     "null: set the lines (e.g. optics.laser_wavelengths_m=[4.5e-7,5.32e-7,6.33e-7]), or search.lsr_over=design for "
     "the design wavelength alone"),
    (("+experiment=joint", "codesign.lsr_over=wavelengths"),
     "codesign.lsr_over = 'wavelengths': takes the worst LSR over the laser lines, and optics.laser_wavelengths_m is "
     "null: set the lines (e.g. optics.laser_wavelengths_m=[4.5e-7,5.32e-7,6.33e-7]), or codesign.lsr_over=design "
     "for the design wavelength alone"),
    (("+experiment=mask_search", LINES, "sensor.wavelength_laser_m=4.5e-7", "search.restorability_alpha_l=1e6"),
     "search.restorability_alpha_l = 1000000.0: counts the laser's saturated footprint at the design wavelength "
     "(6.33e-07 m), not at sensor.wavelength_laser_m = 4.5e-07: set search.restorability_alpha_l=null, or the laser "
     "back to the design wavelength"),
    (("+experiment=export", "optics.wrap_waves=null", "export.levels=8"),
     "export.levels = 8: a continuous surface (optics.wrap_waves = null) has no etch levels: set export.levels=null, "
     "or wrap the surface (optics.wrap_waves=1, or m for an m-wave multi-order plate)"),
    (("+experiment=simulate", "sensor.wavelength_laser_m=5.32e-7"),
     "sensor.wavelength_laser_m = 5.32e-07: must be the design wavelength (6.33e-07) or one of "
     "optics.laser_wavelengths_m (null): the laser's PSF is computed at those lines (add the line to "
     "optics.laser_wavelengths_m)"),
    (("+experiment=psf", "optics.focal_n=640", "optics.laser_wavelengths_m=[6.33e-7,4.5e-7]"),  # smoke: 20 um pupil
     "optics.laser_wavelengths_m[1] = 4.5e-07: at this line the sampled pupil's spectrum repeats every lambda f / "
     "pupil_pitch = 0.002475 m, less than the 0.003456 m window: its PSF would alias; need optics.pupil_pitch_m <= "
     "1.432e-05 m, a smaller optics.focal_n, or a longer line"),
])
def test_line_settings_refused_before_work(monkeypatch, capsys, tmp_path, overrides, message):
    line = config_error(monkeypatch, capsys, tmp_path / "run", *overrides, "debug=smoke")
    assert line == f"codesign: configuration error: {message}"


def test_psf_reports_every_line_and_the_curve(tmp_path):
    run = tmp_path / "psf"
    proc = run_codesign("+experiment=psf", "debug=smoke", LINES, "optics.wrap_waves=null", f"hydra.run.dir={run}",
                        timeout=180)
    assert proc.returncode == 0, proc.stderr[-3000:]
    m = json.loads((run / "metrics.json").read_text())
    block = m["laser_lines"]
    rows = block["mask"]["lines"]
    assert block["wrap_waves"] is None and [r["wavelength_m"] for r in rows] == [4.5e-7, 5.32e-7, 6.33e-7]
    assert rows[2]["lsr"] == pytest.approx(m["lsr"], rel=1e-6)  # the design line is the run's own LSR
    assert block["mask"]["lsr_worst"] == max(r["lsr"] for r in rows)
    for r in rows:
        assert r["lsr_sampled"] <= r["lsr"] * (1 + 1e-9) <= r["lsr_bound"] * (1 + 1e-9)
        assert 0 < r["window_energy"] <= 1 and r["saturated_px"] >= 0
    curve = block["curve"]
    assert len(curve["wavelengths_m"]) == len(curve["lsr"]) >= 29 and 4.5e-7 in curve["wavelengths_m"]
    assert (run / "lsr_wavelength.png").stat().st_size > 10_000


def test_search_over_lines_constrains_the_worst_line(tmp_path):
    run = tmp_path / "search"
    proc = run_codesign("+experiment=mask_search", "debug=smoke", "mask=spiral", LINES, "search.lsr_over=wavelengths",
                        f"hydra.run.dir={run}", timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "LSR: the worst of the lines [450.0, 532.0, 633.0] nm (2 pi-wrapped plate)" in proc.stdout + proc.stderr
    m = json.loads((run / "metrics.json").read_text())
    assert m["lsr_over"] == "wavelengths"
    best = m["laser_lines"]["best"]
    assert m["lsr_worst_line"] == best["lsr_worst"] == max(r["lsr"] for r in best["lines"])
    assert m["lsr_worst_line_published"] == m["laser_lines"]["published"]["lsr_worst"]
    assert best["lines"][2]["lsr"] == pytest.approx(m["lsr"], rel=1e-6)


def test_measured_psf_keeps_the_laser_at_the_design_line(monkeypatch, capsys, tmp_path):
    import numpy as np

    yy, xx = np.mgrid[-16:17, -16:17]
    frame = np.exp(-(xx**2 + yy**2) / (2 * 4.0**2))  # a spread spot, well below the diffraction limit's peak
    np.save(tmp_path / "psf.npy", frame)
    line = config_error(monkeypatch, capsys, tmp_path / "run", "+experiment=simulate", "debug=smoke", LINES,
                        f"optics.psf_file={tmp_path / 'psf.npy'}", "optics.psf_pitch_m=5.4e-6",
                        "sensor.wavelength_laser_m=4.5e-7")
    assert line == ("codesign: configuration error: sensor.wavelength_laser_m = 4.5e-07: a measured PSF "
                    "(optics.psf_file) holds one wavelength, the design's (6.33e-07 m): a laser at another line needs "
                    "the mask's computed PSF there; set sensor.wavelength_laser_m=6.33e-07 or optics.psf_file=null")
