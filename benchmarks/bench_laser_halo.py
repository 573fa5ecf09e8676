"""The laser's saturated area against a float64 reference of the whole sensor (docs/sensor.md Sec. 7).

Reference: the laser PSF evaluated in float64 at every sensor pixel centre of the full sensor (2532 x 2532 at
5.4 um by default) by one matrix Fourier transform from a pupil grid ``--refine`` times finer than the design
grid (so that its period, lambda f / pitch, is several sensor widths: no replica reaches the sensor), plus the
uniform background alpha_b * s of a uniform scene; a sensor pixel saturates where the electrons reach full
well, without noise (c1 = c2 = 0, no read-noise spread, no dark current), so that only the optics differ. The
simulator's direct path saturates a network pixel where the average over it does: the reference's network-pixel
fraction averages its sensor pixels the same way (area, as the full path's downsampling). It shares nothing with
the simulator's laser model (window footprint + far-PSF halo), only the mask, the optics and the sensor numbers.

    python -m benchmarks --only laser_halo [--scale full]     (quick: reference pupil 4x finer; full: 8x)
"""
from __future__ import annotations

import time
from pathlib import Path

import torch
import torch.nn.functional as F

from benchmarks.common import Report, compose, machine, markdown_table, write_json
from codesign.data.params import fixed_scene_params
from codesign.optics.grid import axis_coords
from codesign.optics.propagation import mft, mft_matrix
from codesign.optics.psf import OpticalSystem

ALPHAS = (1e3, 3e3, 1e4, 3e4, 1e5, 3e5, 1e6, 2e6)
ANGLE = (0.008, -0.012)  # (n_u, n_v) rad: the simulate experiment's laser, focal offset (0.88, -1.32) mm
SCENE = 0.5  # uniform radiance of the scene
NOISE_FREE = dict(c1=0.0, c2=0.0, read_noise_std_e=0.0, dark_current_mean_e=0.0)


@torch.no_grad()
def reference_laser(camera, angle=ANGLE, refine: int = 8) -> torch.Tensor:
    """(n, n) float64: h(x - x_l) / h0(0) at every sensor pixel centre (point samples, per sensor pixel), from
    the mask on a pupil grid ``refine`` times finer than the design grid."""
    spec, sensor = camera.system.spec, camera.sensor
    fine = OpticalSystem(spec.replace(pupil_pitch_m=spec.pupil_pitch_m / refine, pupil_n=None,
                                      laser_wavelengths_m=None, scene_spectrum=None),
                         dtype=torch.float64)
    mask = camera.mask.on_grid(fine.grid, spec.aperture_diameter_m)
    field = fine.field(mask.phase().to(torch.float64))
    pupil = axis_coords(fine.grid.n, fine.spec.pupil_pitch_m)
    n, dx, f = sensor.resolution, sensor.pixel_pitch_m, spec.focal_length_m
    centres = (torch.arange(n, dtype=torch.float64) - (n - 1) / 2) * dx  # sensor pixel centres
    spot_y, spot_x = f * angle[1], f * angle[0]  # n_v moves along rows (y), n_u along columns (x)
    e = mft(field, mft_matrix(centres - spot_y, pupil, spec.lambda_f, torch.complex128),
            mft_matrix(centres - spot_x, pupil, spec.lambda_f, torch.complex128))
    scale = (fine.spec.pupil_pitch_m * dx / spec.lambda_f) ** 2 / float((field.abs() ** 2).sum())
    h = (e.real ** 2 + e.imag ** 2) * scale  # energy fraction per sensor pixel (point sample x pixel area)
    return h / fine.uncoded_peak  # the uncoded peak of the same grid and pitch


def saturation_threshold(sensor) -> float:
    """Relative irradiance r = I / I_sat at which the noise-free electrons reach full well (Q_e mu_p = r e_sat,
    plus the read-noise mean)."""
    return 1.0 - sensor.read_noise_mean_e / sensor.full_well_e


@torch.no_grad()
def model_fraction(camera, alpha: float, angle=ANGLE) -> float:
    """Saturated fraction of the network pixels in the simulator (noise-free, uniform scene)."""
    sim = camera.simulator
    optics = camera.frozen_optics()
    scene = torch.full((1, 1, sim.scene_size, sim.scene_size), SCENE, dtype=torch.float32)
    p = fixed_scene_params(1, alpha_l=alpha, laser_angle_rad=list(angle), **NOISE_FREE)
    return float(sim(scene, p, optics.state, seed=0, mask_key=optics.key)["saturated"].float().mean())


def rows(camera, alphas=ALPHAS, refine: int = 8, angle=ANGLE, without_halo=None) -> tuple[list[dict], float]:
    """Per alpha_l: the reference's saturated fraction of sensor pixels and of network pixels, the simulator's
    (and ``without_halo``'s, a camera with sensor.laser_halo=false, when given), the relative error."""
    t0 = time.perf_counter()
    laser = reference_laser(camera, angle, refine)
    seconds = time.perf_counter() - t0
    sensor = camera.sensor
    alpha_b = fixed_scene_params(1).alpha_b.item()
    background, thr = alpha_b * SCENE, saturation_threshold(sensor)
    out = []
    for a in alphas:
        r = background + a * laser
        coarse = F.adaptive_avg_pool2d(r[None, None], sensor.image_size)[0, 0]
        ref = float((coarse >= thr).double().mean())
        model = model_fraction(camera, a, angle)
        row = {"alpha_l": a, "reference_sensor_pixels": float((r >= thr).double().mean()),
               "reference": ref, "model": model, "relative_error": model / ref - 1 if ref else float("nan")}
        if without_halo is not None:
            row["model_without_halo"] = model_fraction(without_halo, a, angle)
        out.append(row)
    return out, seconds


SPLINE_RECORD = Path(__file__).resolve().parent / "results/full/design/spline/best_mask.json.gz"
REFINE = {"quick": 4, "full": 8}


def cameras(*overrides: str) -> tuple:
    """(camera, the same camera with sensor.laser_halo=false) of +experiment=simulate with ``overrides``."""
    from codesign.camera.build import build_camera

    on, off = (compose(["+experiment=simulate", *overrides, *extra]) for extra in ((), ["sensor.laser_halo=false"]))
    return build_camera(on, "cpu"), build_camera(off, "cpu")


def run(scale: str, out: Path) -> Report:
    """The table for the published mask and the searched spline design (docs/sensor.md Sec. 7)."""
    masks = {"published": (), "spline design": ("mask=spline", f"mask.init={SPLINE_RECORD}")}
    data, tables = {"machine": machine(), "scale": scale, "refine": REFINE[scale], "masks": {}}, []
    for name, overrides in masks.items():
        camera, off = cameras(*overrides)
        table, seconds = rows(camera, ALPHAS, REFINE[scale], without_halo=off)
        data["masks"][name] = {"reference_seconds": seconds, "rows": table}
        tables.append(f"**{name} mask** (reference {seconds:.0f} s):\n\n" + markdown_table(
            ["alpha_l", "reference, sensor px", "reference, network px", "model", "error", "window only"],
            [[f"{r['alpha_l']:.0e}", r["reference_sensor_pixels"], r["reference"], r["model"],
              f"{100 * r['relative_error']:+.1f} %", r["model_without_halo"]] for r in table]))
    write_json(out / "laser_halo.json", data)
    print("\n\n".join(tables))
    return Report("laser_halo", "Laser saturated area against a float64 reference of the whole sensor", tables,
                  notes=[f"Reference: the laser PSF at every sensor pixel centre by one float64 MFT from a pupil "
                         f"grid {REFINE[scale]}x finer than the design grid, plus the uniform background, "
                         f"noise-free; network pixels saturate where their sensor pixels' average does. Model: the "
                         f"simulator's direct path (window footprint + far-PSF halo); 'window only': "
                         f"sensor.laser_halo=false. Laser at the simulate experiment's angle."])


if __name__ == "__main__":
    from benchmarks.__main__ import standalone

    standalone(run)
