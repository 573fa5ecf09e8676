"""Sensor-simulation benchmarks: full-resolution vs direct low-resolution path, and the skip paths.

    python -m benchmarks.sensor [--batch 8] [--repeats 3]

Writes benchmarks/results/sensor.json and sensor.png. Images/s on 2 threads at the 256 x 256 network
resolution; error of the direct path against the full path (PSNR of the normalized sensor images outside and
inside saturated areas, saturated-mask agreement), noise-free (systematic) and with the paper's noise; time
saved by each skip, with proof that the outputs are identical.
"""
from __future__ import annotations

import argparse
import math
import time

import torch

from benchmarks.common import RESULTS, machine, write_result


def _setup(path: str = "direct", downsample: str = "area", device=None, **sensor_kw):
    """The default optics (conf/optics/default.yaml) with the published mask frozen: simulator, PSF state, its
    cache key, mask, system; ``sensor_kw`` are further SensorSpec fields."""
    from codesign.optics import OpticalSystem, OpticsSpec
    from codesign.optics.masks import published_halfring
    from codesign.sensor.simulator import SensorSimulator, mask_state_key, psf_state
    from codesign.sensor.spec import SensorSpec

    optics = OpticsSpec(pupil_pitch_m=3.83e-3 / 384)
    system = OpticalSystem(optics, device=device)
    mask = published_halfring(system.grid, optics.aperture_diameter_m)
    with torch.no_grad():
        state = psf_state(system, mask.phase())
    sim = SensorSimulator(SensorSpec(path=path, downsample=downsample, **sensor_kw), optics)
    return sim, state, mask_state_key(mask), mask, system


def _scenes(batch: int, size: int) -> torch.Tensor:
    from codesign.data.scenes import build_scene_source

    src = build_scene_source({"scenes": "builtin"})
    names = src.split_names("all")
    return src.fixed_batch([names[i % len(names)] for i in range(batch)], size)


def _time(fn, repeats: int) -> float:
    fn()
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - t0) / repeats


def _psnr(a: torch.Tensor, b: torch.Tensor, sel: torch.Tensor) -> float:
    if not bool(sel.any()):
        return float("nan")
    mse = float(((a - b)[sel] ** 2).mean())
    return float("inf") if mse == 0 else 10 * math.log10(1.0 / mse)


def paths(batch: int, repeats: int) -> dict:
    from codesign.data.params import fixed_scene_params

    out = {}
    runs = {}
    for name, path, down in (("direct", "direct", "area"), ("full_area", "full", "area"),
                             ("full_bicubic_aa", "full", "bicubic_aa")):
        sim, state, key, _, _ = _setup(path, down)
        scenes = _scenes(batch, sim.scene_size)
        for noise in ("noise_free", "paper_noise"):
            kw = dict(c1=0.0, c2=0.0, read_noise_std_e=0.0, dark_current_mean_e=0.0) if noise == "noise_free" \
                else {}
            for alpha in (0.0, 1e4, 1e6):
                p = fixed_scene_params(batch, alpha_l=alpha, laser_angle_rad=[0.008, -0.012], **kw)
                with torch.no_grad():
                    runs[(name, noise, alpha)] = sim(scenes, p, state, seed=0, mask_key=key)
        p = fixed_scene_params(batch, alpha_l=1e6, laser_angle_rad=[0.008, -0.012])
        with torch.no_grad():
            sec = _time(lambda: sim(scenes, p, state, seed=1, mask_key=key), repeats)
        out[name] = {"seconds_per_batch": sec, "images_per_second": batch / sec}
        print(f"{name:>16}: {batch / sec:8.2f} images/s (batch {batch})", flush=True)
    errors = []
    for ref in ("full_area", "full_bicubic_aa"):
        for noise in ("noise_free", "paper_noise"):
            for alpha in (0.0, 1e4, 1e6):
                a, b = runs[("direct", noise, alpha)], runs[(ref, noise, alpha)]
                sa, sb = a["sensor"], b["sensor"]
                sat = b["saturated"]
                pad = (sa.shape[-1] - sat.shape[-1]) // 2
                inner = lambda t: t[..., pad:pad + sat.shape[-1], pad:pad + sat.shape[-1]]  # noqa: E731
                ia, ib = inner(sa), inner(sb)
                row = {"reference": ref, "noise": noise, "alpha_l": alpha,
                       "psnr_outside_saturation_db": _psnr(ia, ib, ~sat),
                       "psnr_inside_saturation_db": _psnr(ia, ib, sat),
                       "saturated_fraction_full": float(sat.float().mean()),
                       "saturated_fraction_direct": float(a["saturated"].float().mean()),
                       "saturated_mask_agreement": float((a["saturated"] == sat).float().mean())}
                errors.append(row)
                print(f"direct vs {ref:>15} {noise:>11} alpha_l {alpha:8.0e}: PSNR out {row['psnr_outside_saturation_db']:6.2f} dB"
                      f" in {row['psnr_inside_saturation_db']:6.2f} dB, sat. {row['saturated_fraction_direct']:.4f}"
                      f" vs {row['saturated_fraction_full']:.4f}, mask agreement {row['saturated_mask_agreement']:.4f}",
                      flush=True)
    out["errors"] = errors
    return out


def skips(batch: int, repeats: int) -> dict:
    from codesign.data.params import fixed_scene_params
    from codesign.sensor.simulator import SensorSimulator

    sim, state, key, mask, system = _setup("direct")
    ref = SensorSimulator(sim.sensor, sim.optics, skip_unneeded=False)
    scenes = _scenes(batch, sim.scene_size)
    cases = {
        "no_laser (alpha_l = 0)": dict(alpha_l=0.0),
        "laser outside the field": dict(alpha_l=1e6, laser_angle_rad=[0.2, 0.2]),
        "zero noise terms": dict(alpha_l=0.0, c1=0.0, c2=0.0, read_noise_std_e=0.0, dark_current_mean_e=0.0),
    }
    rows = []
    for name, kw in cases.items():
        p = fixed_scene_params(batch, **kw)
        with torch.no_grad():
            a, b = sim(scenes, p, state, seed=3, mask_key=key), ref(scenes, p, state, seed=3, mask_key=key)
            t_skip = _time(lambda: sim(scenes, p, state, seed=3, mask_key=key), repeats)
            t_full = _time(lambda: ref(scenes, p, state, seed=3, mask_key=key), repeats)
        same = all(torch.equal(a[k], b[k]) for k in a)
        rows.append({"case": name, "seconds_skip": t_skip, "seconds_full": t_full, "identical": same})
    p = fixed_scene_params(batch, alpha_l=1e4, laser_angle_rad=[0.008, -0.012])
    with torch.no_grad():
        def fresh():
            from codesign.sensor.simulator import psf_state
            st = psf_state(system, mask.phase())
            return sim(scenes, p, st, seed=3, mask_key=None)

        def cached():
            return sim(scenes, p, state, seed=3, mask_key=key)

        same = all(torch.equal(x, y) for x, y in zip(fresh().values(), cached().values()))
        rows.append({"case": "frozen-mask PSF/OTF cache", "seconds_skip": _time(cached, repeats),
                     "seconds_full": _time(fresh, repeats), "identical": same})
    for r in rows:
        print(f"{r['case']:>28}: {1e3 * r['seconds_skip']:8.1f} ms with the skip, {1e3 * r['seconds_full']:8.1f} ms "
              f"without ({r['seconds_full'] / r['seconds_skip']:.2f}x), identical outputs: {r['identical']}")
    return {"rows": rows}


def plot(data: dict) -> None:
    from codesign.io.files import save_figure
    from codesign.io.plots import plt

    fig, ax = plt.subplots(figsize=(6.2, 4))
    for ref, marker in (("full_area", "o"), ("full_bicubic_aa", "s")):
        for noise, color in (("noise_free", "C0"), ("paper_noise", "C1")):
            rows = [r for r in data["paths"]["errors"] if r["reference"] == ref and r["noise"] == noise]
            t = 1.0 / data["paths"]["direct"]["images_per_second"]
            ax.scatter([t] * len(rows), [r["psnr_outside_saturation_db"] for r in rows], marker=marker, color=color,
                       label=f"direct vs {ref}, {noise}")
    for name in ("full_area", "full_bicubic_aa"):
        ax.axvline(1.0 / data["paths"][name]["images_per_second"], ls=":", color="0.5")
        ax.annotate(name, (1.0 / data["paths"][name]["images_per_second"], ax.get_ylim()[0]), fontsize=7,
                    rotation=90, va="bottom")
    ax.set(xscale="log", xlabel="seconds per image (batch 8, 2 threads)",
           ylabel="PSNR of direct vs full, outside saturation [dB]",
           title="sensor simulation: direct low-resolution path against the full path")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    save_figure(RESULTS / "sensor.png", fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    torch.set_num_threads(2)
    data = {"machine": machine(), "batch": a.batch, "paths": paths(a.batch, a.repeats),
            "skips": skips(a.batch, max(a.repeats, 5))}
    write_result("sensor", data)
    plot(data)


if __name__ == "__main__":
    main()
