"""Re-measure the stored designs (benchmarks/results/full/design/*/best_mask.json) where issue 37 asks: at the
certified continuous peak, and at the common laser lines as the plate would be made. A study of stored records, not
a timing.

    python -m benchmarks.design_peaks continuous [NAME ...]   # design_peaks: continuous_lsr.json
    python -m benchmarks.design_peaks lines [NAME ...]          # wavelength_lsr.json (all stored designs)
    python -m benchmarks.design_peaks wrapping NAME             # wrapping_NAME.json
    python -m benchmarks.design_peaks whole NAME                # whole_NAME.json
    python -m benchmarks.design_peaks curves NAME               # wrapping_NAME.png

continuous: for each record, the LSR it reports (refined with the former top-8, +-1 sample search), the certified
continuous peak on its own optics, and the re-check (codesign.design.check: a pupil grid finer by the family's
factor and a window twice as wide), all in float64, and LSR / limit with the record's limit (its mtf_mean and
window energy are unchanged).

lines: a plate made for the design wavelength lambda0 (633 nm) in a material of index n(lambda) has the surface
height h = wrap(phi0) lambda0 / (2 pi (n(lambda0) - 1)) (smooth: the continuous surface; wrapped: phi0 modulo
2 pi, the usual diffractive plate; m-wave: modulo 2 pi m, a multi-order plate). A laser at lambda sees the phase
2 pi (n(lambda) - 1) h / lambda (codesign/optics/lines.py): off lambda0 the wrap's steps are no longer whole waves
and light returns to a zero order. For every mask, surface and line: the certified continuous LSR on the design's
own window and pupil grid at that wavelength, the window energy (the share of the PSF the window holds) and the
saturated area at alpha_l = 1e6.

wrapping NAME: one design's surfaces side by side (smooth, wrapped, 2- and 4-wave): depth, the lines' LSRs, the
design line's mtf_mean and the fabrication yield of +experiment=tolerance (default sources) for each surface. All
write their JSON atomically and print a table.

whole NAME: the lines' table of one design on a window twice as wide, its pupil grid fine enough for 405 nm there:
whether the design's window held the whole PSF at every line.

curves NAME: the certified LSR against wavelength (400-1100 nm) of one design made as each surface, one figure.
"""
from __future__ import annotations

import json
import math
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from codesign.design.check import verify_design
from codesign.optics.lines import LaserLines
from codesign.optics.materials import Material
from codesign.optics.metrics import RadialMTF, mtf
from codesign.fab.laser_lines import lsr_curve, lsr_wavelength_figure, surface_name
from codesign.io.files import save_figure, write_json
from codesign.optics import OpticalSystem, OpticsSpec, build_mask
from codesign.optics.grid import PupilGrid
from codesign.optics.masks import config_of_design, published_halfring

DESIGNS = Path(__file__).resolve().parent / "results/full/design"
BAND = (0.0, 0.5)
LINES_NM = (405.0, 450.0, 532.0, 633.0, 1064.0)
RECORDS = ("spiral", "spline", "pixel", "spline_grids2", "spline_whole_window", "spline_multistart", "spiral_visible",
           "spline_visible")
WRAPS = (None, 1, 2)  # the continuous surface, the 2 pi-wrapped plate, a 2-wave multi-order plate


def measure(folder: Path) -> dict:
    path = folder / "best_mask.json"
    raw = json.loads(path.read_text())
    spec = OpticsSpec(**raw["optics"])
    grid = PupilGrid.from_spec(spec, dtype=torch.float64)
    mask = build_mask(config_of_design({"kind": raw["kind"], "init": str(path)}), grid, spec.aperture_diameter_m)
    t = time.perf_counter()
    check = verify_design(mask.freeze(), spec, BAND, 0.02, dtype=torch.float64)
    out = {"kind": raw["kind"], "focal_n": spec.focal_n, "pupil_n": spec.grid_n, "lsr_reported": raw["lsr"],
           "lsr_limit": raw.get("lsr_limit"), "mtf_mean": check["design"]["mtf_mean"],
           **{f"lsr_{k}": check[k]["lsr"] for k in ("design", "fine", "whole")},
           "lsr_sampled": check["design"]["lsr_sampled"], "window_energy_whole": check["whole"]["window_energy"],
           "whole_focal_n": check["whole"]["focal_n"], "seconds": time.perf_counter() - t}
    out["lsr_over_reported"] = out["lsr_design"] / out["lsr_reported"] - 1
    if out["lsr_limit"]:
        out["lsr_over_limit"] = out["lsr_design"] / out["lsr_limit"]
        out["lsr_whole_over_limit"] = out["lsr_whole"] / out["lsr_limit"]
    return out


def continuous(names: list[str]) -> None:
    torch.set_num_threads(max(1, torch.get_num_threads()))
    folders = [DESIGNS / n for n in names] if names else sorted(p.parent for p in DESIGNS.glob("*/best_mask.json"))
    rows = {}
    print(f"{'design':26s} {'window':>6s} {'reported':>10s} {'continuous':>10s} {'+%':>6s} {'fine':>10s} "
          f"{'whole':>10s} {'/limit':>6s} {'whole/lim':>9s} {'s':>6s}", flush=True)
    for folder in folders:
        r = rows[folder.name] = measure(folder)
        print(f"{folder.name:26s} {r['focal_n']:6d} {r['lsr_reported']:10.4e} {r['lsr_design']:10.4e} "
              f"{100 * r['lsr_over_reported']:6.2f} {r['lsr_fine']:10.4e} {r['lsr_whole']:10.4e} "
              f"{r.get('lsr_over_limit', float('nan')):6.3f} {r.get('lsr_whole_over_limit', float('nan')):9.3f} "
              f"{r['seconds']:6.1f}", flush=True)
    if not names:
        write_json(DESIGNS / "continuous_lsr.json", {
            "machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads",
            "torch": torch.__version__, "python": platform.python_version(), "date": time.strftime("%Y-%m-%d"),
            "command": "python -m benchmarks.design_peaks continuous", "designs": rows})


def design_phase(name: str, pupil_pitch_m: float | None = None) -> tuple[torch.Tensor, OpticsSpec, float | None]:
    """(phase at the design wavelength, its optics, its plate cell) of the published mask or a stored record;
    ``pupil_pitch_m``: evaluate it on a finer pupil grid (analytic and spline families), e.g. so that a wide window
    holds the short lines."""
    if name == "published":
        spec = OpticsSpec()
        grid = PupilGrid.from_spec(spec, dtype=torch.float64)
        return published_halfring(grid, spec.aperture_diameter_m).phase().detach(), spec, None
    path = DESIGNS / name / "best_mask.json"
    raw = json.loads(path.read_text())
    spec = OpticsSpec(**raw["optics"])
    if pupil_pitch_m is not None:
        spec = spec.replace(pupil_pitch_m=pupil_pitch_m, pupil_n=None, laser_wavelengths_m=None,
                            scene_spectrum=None)
    grid = PupilGrid.from_spec(spec, dtype=torch.float64)
    mask = build_mask(config_of_design({"kind": raw["kind"], "init": str(path)}), grid, spec.aperture_diameter_m)
    return mask.phase().detach().to(torch.float64), spec, mask.plate_cell_m


def line_table(phase0: torch.Tensor, spec: OpticsSpec, material: Material, cell: float | None, wrap) -> dict:
    """The per-line rows of a design made as ``wrap`` (codesign.optics.lines: the one implementation the
    experiments use), with "aliased" (None) where the design's pupil grid cannot hold its window at a line."""
    out = {}
    for nm in LINES_NM:
        problem = spec.line_problem(nm * 1e-9)
        if problem is not None:
            out[str(int(nm))] = {"lsr": None, "window_energy": None}
            continue
        system = OpticalSystem(spec.replace(laser_wavelengths_m=[nm * 1e-9], wrap_waves=wrap), dtype=torch.float64)
        row = LaserLines(system, material.index).table(phase0, cell)[0]
        out[str(int(nm))] = {k: row[k] for k in ("lsr", "lsr_bound", "window_energy", "saturated_px")}
    visible = [out[k]["lsr"] for k in ("450", "532", "633") if out[k]["lsr"] is not None]
    out["worst_visible"] = max(visible) if len(visible) == 3 else None
    every = [out[str(int(nm))]["lsr"] for nm in LINES_NM]
    out["worst_all"] = max(every) if None not in every else None
    return out


def _cell(v: float | None) -> str:
    return f"{v:9.3e}" if v is not None else f"{'aliased':>9s}"


def _surface(wrap) -> str:
    return "smooth" if wrap is None else ("wrapped" if wrap == 1 else f"{wrap}-wave")


def lines(names: list[str]) -> None:
    material = Material()
    rows: dict = {}
    print(f"{'mask':22s} {'surface':9s} " + " ".join(f"{int(w):>9d}" for w in LINES_NM) + "   worst(450-633)",
          flush=True)
    for name in names or ("published", *RECORDS):
        if name != "published" and not (DESIGNS / name / "best_mask.json").is_file():
            continue
        phase0, spec, cell = design_phase(name)
        for wrap in WRAPS:
            out = rows[f"{name}/{_surface(wrap)}"] = line_table(phase0, spec, material, cell, wrap)
            print(f"{name:22s} {_surface(wrap):9s} " + " ".join(_cell(out[str(int(w))]["lsr"]) for w in LINES_NM)
                  + f"   {_cell(out['worst_visible'])}", flush=True)
    if not names:
        write_json(DESIGNS / "wavelength_lsr.json", {
            "machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads",
            "torch": torch.__version__, "date": time.strftime("%Y-%m-%d"), "material": material.name,
            "lines_nm": list(LINES_NM), "command": "python -m benchmarks.design_peaks lines", "masks": rows})


def whole(name: str) -> None:
    """One design at the lines on a window twice as wide (and a pupil grid fine enough for the shortest line there):
    the whole PSF at every line, its LSR against the design window's."""
    material = Material()
    _, spec0, _ = design_phase(name)
    wide = spec0.replace(focal_n=2 * spec0.focal_n, laser_wavelengths_m=None)
    pitch = min(wide.pupil_pitch_m, min(LINES_NM) * 1e-9 * wide.focal_length_m / wide.focal_extent_m * 0.98)
    phase0, spec, cell = design_phase(name, pupil_pitch_m=pitch)
    spec = spec.replace(focal_n=wide.focal_n)
    rows = {}
    for wrap in WRAPS:
        rows[_surface(wrap)] = out = line_table(phase0, spec, material, cell, wrap)
        print(f"{name:22s} {_surface(wrap):9s} " + " ".join(_cell(out[str(int(w))]["lsr"]) for w in LINES_NM)
              + f"   {_cell(out['worst_visible'])}; window energy "
              + " ".join(f"{out[str(int(w))]['window_energy']:.6f}" for w in LINES_NM), flush=True)
    write_json(DESIGNS / f"whole_{name}.json", {
        "machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads",
        "torch": torch.__version__, "date": time.strftime("%Y-%m-%d"), "material": material.name, "design": name,
        "focal_n": spec.focal_n, "pupil_pitch_m": spec.pupil_pitch_m, "pupil_n": spec.grid_n,
        "lines_nm": list(LINES_NM), "command": f"python -m benchmarks.design_peaks whole {name}", "surfaces": rows})


def curves(name: str) -> None:
    """LSR against wavelength (400-1100 nm) of one design made as each surface: one figure, wrapping_NAME.png."""
    material = Material()
    phase0, spec, cell = design_phase(name)
    out = {}
    for wrap in (None, 1, 2, 4):
        system = OpticalSystem(spec.replace(wrap_waves=wrap, laser_wavelengths_m=None), dtype=torch.float64)
        out[f"{_surface(wrap)} ({surface_name(wrap)})"] = lsr_curve(
            system, material, lambda ls: [ls.phase(phase0, i) for i in range(len(ls))], cell)
    save_figure(DESIGNS / f"wrapping_{name}.png", lsr_wavelength_figure(
        out, spec.wavelength_m, (450e-9, 532e-9, 633e-9), f"{name} made for {spec.wavelength_m * 1e9:.0f} nm in "
        f"{material.name}: certified LSR against the laser's wavelength, per surface"))
    print(f"wrote {DESIGNS / f'wrapping_{name}.png'}")


def _tolerance(name: str, wrap, out_dir: Path) -> dict:
    """``+experiment=tolerance`` of a stored design made as ``wrap`` (default sources and samples): its yield."""
    run = out_dir / f"tolerance_{name}_{_surface(wrap)}"
    wrap_arg = "null" if wrap is None else str(wrap)
    cmd = [sys.executable, "-m", "codesign", "+experiment=tolerance", f"mask.init={DESIGNS / name / 'best_mask.json'}",
           f"mask={json.loads((DESIGNS / name / 'best_mask.json').read_text())['kind']}",
           f"optics.wrap_waves={wrap_arg}", f"hydra.run.dir={run}"]
    t = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    m = json.loads((run / "metrics.json").read_text())
    src = m["sources"]
    return {"yield": m["yield"], "lsr_ceiling": m["lsr_ceiling"], "nominal_lsr": m["nominal_lsr"],
            "lsr_p95": m["all_sources"]["lsr_p95"], "depth_scale_lsr_std": src["depth_scale"]["lsr_std"],
            "depth_scale_yield": src["depth_scale"].get("yield"), "seconds": time.perf_counter() - t}


def wrapping(name: str) -> None:
    """The surfaces of one design side by side: depth, the lines' LSRs (worst visible, worst of all), mtf_mean at
    the design line (the same phase modulo 2 pi for every surface) and the tolerance experiment's yield."""
    material = Material()
    phase0, spec, cell = design_phase(name)
    system = OpticalSystem(spec, dtype=torch.float64)
    inside = system.grid.aperture > 0
    full_wave = spec.wavelength_m / (material.index(spec.wavelength_m) - 1)
    relief = float(phase0[inside].max() - phase0[inside].min()) / (2 * math.pi) * full_wave
    radial = RadialMTF(spec)
    with torch.no_grad():
        mtf_mean = float(radial.summary(radial(mtf(system.psf(phase0, cell).to(torch.float64))), BAND)[0])
    rows = {}
    tmp = Path(tempfile.mkdtemp(prefix="wrapping_"))
    print(f"{name}: mtf_mean {mtf_mean:.4g} at {spec.wavelength_m * 1e9:.0f} nm for every surface")
    print(f"{'surface':9s} {'depth um':>9s} " + " ".join(f"{int(w):>9d}" for w in LINES_NM)
          + f" {'worst vis':>9s} {'yield':>6s} {'s':>5s}", flush=True)
    for wrap in (None, 1, 2, 4):
        out = line_table(phase0, spec, material, cell, wrap)
        out["depth_m"] = relief if wrap is None else wrap * full_wave
        out["mtf_mean"] = mtf_mean
        out["tolerance"] = _tolerance(name, wrap, tmp)
        rows[_surface(wrap)] = out
        print(f"{_surface(wrap):9s} {out['depth_m'] * 1e6:9.3f} " + " ".join(
            _cell(out[str(int(w))]["lsr"]) for w in LINES_NM) + f" {_cell(out['worst_visible'])} "
            f"{100 * out['tolerance']['yield']:5.1f}% {out['tolerance']['seconds']:5.0f}", flush=True)
    write_json(DESIGNS / f"wrapping_{name}.json", {
        "machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads",
        "torch": torch.__version__, "date": time.strftime("%Y-%m-%d"), "material": material.name,
        "design": name, "lines_nm": list(LINES_NM), "command": f"python -m benchmarks.design_peaks wrapping {name}",
        "tolerance": "+experiment=tolerance defaults (export.pitch_m 2 um, continuous heights; depth 3 %, level "
                     "noise 10 nm, shift 10 um, rotation 0.5 deg, wavelength 2 nm, defocus 50 um; yield: LSR <= 1.2 x "
                     "nominal)", "surfaces": rows})


USAGE = ("usage: python -m benchmarks.design_peaks continuous [NAME ...] | lines [NAME ...] | wrapping NAME | "
         "whole NAME | curves NAME")


def main(argv: list[str]) -> None:
    single = {"wrapping": wrapping, "whole": whole, "curves": curves}
    if not argv or argv[0] not in ("continuous", "lines", *single) or (argv[0] in single and len(argv) != 2):
        raise SystemExit(USAGE)
    single[argv[0]](argv[1]) if argv[0] in single else {"continuous": continuous, "lines": lines}[argv[0]](argv[1:])


if __name__ == "__main__":
    main(sys.argv[1:])
