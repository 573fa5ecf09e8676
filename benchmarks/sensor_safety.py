"""Float32 safety of the sensor simulation against a float64 reference, alpha_l from 0 to 1e8.

    python -m benchmarks.sensor_safety

For each laser strength and position: NaN/Inf count, and the largest |DN_float32 - DN_float64| outside the
laser's PSF support (the footprint-sized block around its centre pixel) and inside it. Same seed: the noise is
drawn in float64 for both precisions, so the difference is round-off only. Writes results/sensor_safety.json.
"""
from __future__ import annotations

import torch

from benchmarks.common import machine, write_result


def main() -> None:
    torch.set_num_threads(2)
    from codesign.data.params import fixed_scene_params
    from codesign.data.scenes import build_scene_source
    from codesign.optics import OpticalSystem, OpticsSpec
    from codesign.optics.masks import published_halfring
    from codesign.sensor.simulator import SensorSimulator, psf_state
    from codesign.sensor.spec import SensorSpec

    optics = OpticsSpec(pupil_pitch_m=3.83e-3 / 384)
    sims, states = {}, {}
    for dt in (torch.float32, torch.float64):
        system = OpticalSystem(optics, dtype=dt)
        mask = published_halfring(system.grid, optics.aperture_diameter_m)
        with torch.no_grad():
            states[dt] = psf_state(system, mask.phase())
        sims[dt] = SensorSimulator(SensorSpec(), optics)
    sim = sims[torch.float32]
    src = build_scene_source({"scenes": "builtin"})
    scenes = src.fixed_batch(["camera", "astronaut"], sim.scene_size).to(torch.float64)
    n, ks, pitch, f = sim.sensor.image_size, sim.footprint_size(sim.coarse), sim.coarse.pitch, optics.focal_length_m
    positions = {"centre": [0.0, 0.0], "sub-pixel": [0.37 * pitch / f, -0.21 * pitch / f],
                 "edge": [0.0, (n / 2 - 3) * pitch / f], "outside": [0.0, 0.2]}
    rows = []
    for name, ang in positions.items():
        for alpha in (0.0, 1.0, 1e2, 1e4, 1e6, 1e8):
            out = {}
            for dt in (torch.float32, torch.float64):
                p = fixed_scene_params(2, dtype=dt, alpha_l=alpha, laser_angle_rad=ang)
                with torch.no_grad():
                    out[dt] = sims[dt](scenes.to(dt), p, states[dt], seed=5)
            a, b = out[torch.float32]["sensor_dn"].double(), out[torch.float64]["sensor_dn"]
            finite = all(bool(torch.isfinite(v.double()).all()) for v in out[torch.float32].values())
            pos = torch.tensor(ang, dtype=torch.float64).flip(-1) * f / pitch + (n - 1) / 2  # (n_u, n_v) -> (row, col)
            c = torch.round(pos).long()
            near = torch.zeros(n, n, dtype=torch.bool)
            near[max(int(c[0]) - ks // 2, 0): max(int(c[0]) + ks // 2 + 1, 0),
                 max(int(c[1]) - ks // 2, 0): max(int(c[1]) + ks // 2 + 1, 0)] = True
            d = (a - b).abs()[:, 0]
            far = d[:, ~near]
            rows.append({"position": name, "alpha_l": alpha, "finite": finite,
                         "max_abs_dn_outside_support": float(far.max()),
                         "max_abs_dn_inside_support": float(d[:, near].max()) if bool(near.any()) else 0.0,
                         "saturated_mask_equal_outside": bool(torch.equal(
                             out[torch.float32]["saturated"][:, 0][:, ~near], out[torch.float64]["saturated"][:, 0][:, ~near]))})
            r = rows[-1]
            print(f"{name:>9} alpha_l {alpha:7.0e}: finite {finite}, max |DN32-DN64| outside support "
                  f"{r['max_abs_dn_outside_support']:.3g}, inside {r['max_abs_dn_inside_support']:.3g}, "
                  f"saturated masks equal outside: {r['saturated_mask_equal_outside']}", flush=True)
    write_result("sensor_safety", {"machine": machine(), "rows": rows})


if __name__ == "__main__":
    main()
