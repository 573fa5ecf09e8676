"""The laser's saturated area against a float64 reference of the whole sensor (docs/sensor.md Sec. 7).

Reference: the laser PSF evaluated in float64 at every sensor pixel centre of the full sensor (2532 x 2532 at
5.4 um by default) by one matrix Fourier transform from a pupil grid ``--refine`` times finer than the design
grid (so that its period, lambda f / pitch, is several sensor widths: no replica reaches the sensor), plus the
uniform background alpha_b * s of a uniform scene; a sensor pixel saturates where the electrons reach full
well, without noise (c1 = c2 = 0, no read-noise spread, no dark current), so that only the optics differ. The
simulator's direct path saturates a network pixel where the average over it does: the reference's network-pixel
fraction averages its sensor pixels the same way (area, as the full path's downsampling). It shares nothing with
the simulator's laser model (window footprint + far-PSF halo), only the mask, the optics and the sensor numbers.

    python -m benchmarks.laser_halo [--refine 8] [--alphas 1e3,...] [--out benchmarks/results/laser_halo.json]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
import torch.nn.functional as F

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
    fine = OpticalSystem(spec.replace(pupil_pitch_m=spec.pupil_pitch_m / refine, pupil_n=None),
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


def main(argv=None) -> None:
    from hydra import compose, initialize_config_dir

    from codesign.camera.build import build_camera

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--refine", type=int, default=8, help="reference pupil grid: this many times finer")
    ap.add_argument("--alphas", default=",".join(f"{a:g}" for a in ALPHAS))
    ap.add_argument("--out", default="benchmarks/results/laser_halo.json")
    ap.add_argument("overrides", nargs="*", help="Hydra overrides of +experiment=simulate (e.g. mask=spline ...)")
    args = ap.parse_args(argv)
    conf = Path(__file__).resolve().parent.parent / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose("config", overrides=["+experiment=simulate", *args.overrides])
        cfg_off = compose("config", overrides=["+experiment=simulate", *args.overrides, "sensor.laser_halo=false"])
    camera, off = build_camera(cfg, "cpu"), build_camera(cfg_off, "cpu")
    alphas = [float(a) for a in args.alphas.split(",")]
    table, seconds = rows(camera, alphas, args.refine, without_halo=off)
    print(f"reference: pupil {camera.system.spec.grid_n} x {args.refine}, sensor {camera.sensor.resolution}^2 "
          f"float64, {seconds:.1f} s")
    print(f"{'alpha_l':>8} {'ref (sensor px)':>16} {'ref (net px)':>13} {'model':>8} {'rel. err':>9} {'no halo':>8}")
    for r in table:
        print(f"{r['alpha_l']:8.0e} {r['reference_sensor_pixels']:16.5f} {r['reference']:13.5f} {r['model']:8.5f} "
              f"{100 * r['relative_error']:8.2f}% {r['model_without_halo']:8.5f}")
    from benchmarks.common import machine

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps({"machine": machine(), "refine": args.refine, "overrides": args.overrides,
                               "reference_seconds": seconds, "rows": table}, indent=2))
    tmp.replace(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
