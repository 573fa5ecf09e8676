"""Re-measure the stored designs (benchmarks/results/full/design/*/best_mask.json) where issue 37 asks: at the
certified continuous peak, and at the common laser lines as the plate would be made. A study of stored records, not
a timing (as codesign_study.py and early_steps.py run experiments).

    python -m benchmarks.design_peaks continuous [NAME ...]   # design_peaks: continuous_lsr.json
    python -m benchmarks.design_peaks lines                     # wavelength_lsr.json

continuous: for each record, the LSR it reports (refined with the former top-8, +-1 sample search), the certified
continuous peak on its own optics, and the re-check (codesign.design.check: a pupil grid finer by the family's
factor and a window twice as wide), all in float64, and LSR / limit with the record's limit (its mtf_mean and
window energy are unchanged).

lines: a plate made for the design wavelength lambda0 (633 nm) in a material of index n(lambda) has the surface
height h = phi0 lambda0 / (2 pi (n(lambda0) - 1)) (unwrapped: the continuous surface; wrapped: phi0 taken modulo
2 pi first, the usual diffractive plate). A laser at lambda sees the phase 2 pi (n(lambda) - 1) h / lambda: off
lambda0 the wrapped plate's 2 pi steps are no longer 2 pi and light returns to the zero order. For every mask and
line: the certified continuous LSR on the design's own window and pupil grid at that wavelength, and the window
energy (the share of the PSF the window holds). Both write their JSON atomically and print a table.
"""
from __future__ import annotations

import json
import math
import platform
import sys
import time
from pathlib import Path

import torch

from codesign.design.check import verify_design
from codesign.errors import ConfigError
from codesign.fab.materials import Material
from codesign.io.files import write_json
from codesign.optics import OpticalSystem, OpticsSpec, build_mask
from codesign.optics.grid import PupilGrid
from codesign.optics.masks import config_of_design, published_halfring

DESIGNS = Path(__file__).resolve().parent / "results/full/design"
BAND = (0.0, 0.5)
LINES_NM = (405.0, 450.0, 532.0, 633.0, 1064.0)
RECORDS = ("spiral", "spline", "pixel", "spline_grids2", "spline_whole_window")


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


def design_phase(name: str) -> tuple[torch.Tensor, OpticsSpec, float | None]:
    """(phase at the design wavelength, its optics, its plate cell) of the published mask or a stored record."""
    if name == "published":
        spec = OpticsSpec()
        grid = PupilGrid.from_spec(spec, dtype=torch.float64)
        return published_halfring(grid, spec.aperture_diameter_m).phase().detach(), spec, None
    path = DESIGNS / name / "best_mask.json"
    raw = json.loads(path.read_text())
    spec = OpticsSpec(**raw["optics"])
    grid = PupilGrid.from_spec(spec, dtype=torch.float64)
    mask = build_mask(config_of_design({"kind": raw["kind"], "init": str(path)}), grid, spec.aperture_diameter_m)
    return mask.phase().detach().to(torch.float64), spec, mask.plate_cell_m


def at_line(phase0: torch.Tensor, spec: OpticsSpec, material: Material, wavelength_m: float, wrapped: bool):
    """(system at the line, the plate's phase there)."""
    n0, n1 = material.index(spec.wavelength_m), material.index(wavelength_m)
    surface = torch.remainder(phase0, 2 * math.pi) if wrapped else phase0
    height = surface * spec.wavelength_m / (2 * math.pi * (n0 - 1))
    system = OpticalSystem(spec.replace(wavelength_m=wavelength_m), dtype=torch.float64)
    return system, 2 * math.pi * (n1 - 1) * height / wavelength_m


def _cell(v: float | None) -> str:
    return f"{v:9.3e}" if v is not None else f"{'aliased':>9s}"


def lines() -> None:
    material = Material()
    rows: dict = {}
    print(f"{'mask':22s} {'surface':9s} " + " ".join(f"{int(w):>9d}" for w in LINES_NM) + "   worst(450-633)",
          flush=True)
    for name in ("published", *RECORDS):
        if name != "published" and not (DESIGNS / name / "best_mask.json").is_file():
            continue
        phase0, spec, cell = design_phase(name)
        for wrapped in (False, True):
            key = f"{name}/{'wrapped' if wrapped else 'unwrapped'}"
            out = {}
            for nm in LINES_NM:
                try:
                    system, phase = at_line(phase0, spec, material, nm * 1e-9, wrapped)
                except ConfigError:  # the design's pupil grid aliases its window at this line: not measured
                    out[str(int(nm))] = {"lsr": None, "window_energy": None}
                    continue
                peak = system.continuous_peak(phase, cell_m=cell)
                out[str(int(nm))] = {"lsr": peak.value / system.uncoded_peak,
                                     "window_energy": float(system.psf(phase, cell).sum())}
            visible = [out[k]["lsr"] for k in ("450", "532", "633") if out[k]["lsr"] is not None]
            out["worst_visible"] = max(visible) if len(visible) == 3 else None
            rows[key] = out
            print(f"{name:22s} {'wrapped' if wrapped else 'smooth':9s} "
                  + " ".join(_cell(out[str(int(w))]["lsr"]) for w in LINES_NM)
                  + f"   {_cell(out['worst_visible'])}", flush=True)
    write_json(DESIGNS / "wavelength_lsr.json", {
        "machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads",
        "torch": torch.__version__, "date": time.strftime("%Y-%m-%d"), "material": material.name,
        "lines_nm": list(LINES_NM), "command": "python -m benchmarks.design_peaks lines", "masks": rows})


def main(argv: list[str]) -> None:
    if not argv or argv[0] not in ("continuous", "lines") or (argv[0] == "lines" and len(argv) > 1):
        raise SystemExit("usage: python -m benchmarks.design_peaks continuous [NAME ...] | lines")
    continuous(argv[1:]) if argv[0] == "continuous" else lines()


if __name__ == "__main__":
    main(sys.argv[1:])
