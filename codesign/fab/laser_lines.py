"""The laser lines of a run (``optics.laser_wavelengths_m``, the surface of ``optics.wrap_waves`` in ``material.*``):
the LaserLines of its optics, the per-line table a run reports, and the LSR-against-wavelength figure."""
from __future__ import annotations

import logging

import numpy as np
import torch

from codesign.errors import ConfigError
from codesign.optics.materials import Material
from codesign.io.plots import plt
from codesign.optics.lines import COMMON_LINES_M, LaserLines, curve_wavelengths, worst

log = logging.getLogger("codesign.fab")


def run_lines(material: Material, system, need: str | None = None) -> LaserLines | None:
    """The LaserLines of ``system``'s laser lines through ``material`` (material.*), or None when
    optics.laser_wavelengths_m is null; ``need``: the key that asks for them (ConfigError naming it when no lines
    are set)."""
    spec = system.spec
    if spec.laser_wavelengths_m is None:
        if need is not None:
            raise ConfigError(need, "wavelengths", "takes the worst LSR over the laser lines, and "
                              "optics.laser_wavelengths_m is null: set the lines (e.g. "
                              f"optics.laser_wavelengths_m=[4.5e-7,5.32e-7,6.33e-7]), or {need}=design for the design "
                              "wavelength alone")
        return None
    for w in (spec.wavelength_m, *spec.laser_wavelengths_m):
        material.check_wavelength(w)
    return LaserLines(system, material.index)


def lines_summary(lines: LaserLines, phases: dict, cell_m: float | None = None) -> dict:
    """metrics.json's ``laser_lines`` block: the per-line table of each named phase (the design phase, or a list of
    the phases each line sees), its worst line, and how the surface is made."""
    out = {"wrap_waves": lines.wrap, "wavelengths_m": list(lines.wavelengths)}
    for name, phase in phases.items():
        rows = lines.table(phase, cell_m) if torch.is_tensor(phase) else lines.table_of_phases(phase, cell_m)
        w = worst(rows)
        out[name] = {"lines": rows, "lsr_worst": w["lsr"], "worst_wavelength_m": w["wavelength_m"]}
    return out


def log_lines(summary: dict, name: str, label: str) -> None:
    """One log line of a ``lines_summary`` entry ``name``: the LSR at every laser line and the worst, under
    ``label``."""
    rows = summary[name]["lines"]
    log.info("%s at the laser lines (%s): %s; worst %.4g at %.0f nm", label, surface_name(summary["wrap_waves"]),
             ", ".join(f"{r['wavelength_m'] * 1e9:.0f} nm LSR {r['lsr']:.4g}" for r in rows),
             summary[name]["lsr_worst"], summary[name]["worst_wavelength_m"] * 1e9)


def surface_name(wrap_waves: int | None) -> str:
    """How a surface of ``wrap_waves`` (optics.wrap_waves) is called in logs and figures."""
    return "continuous surface" if wrap_waves is None else ("2 pi-wrapped plate" if wrap_waves == 1 else
                                                          f"{wrap_waves}-wave multi-order plate")


def lsr_curve(system, material: Material, phases_of, cell_m: float | None = None, extra: tuple = ()) -> dict:
    """LSR (certified peak) against wavelength over the plot's range: ``phases_of(lines)`` gives the list of phases
    each of a LaserLines' lines sees. Wavelengths the window would alias, or outside the material's fit, are left
    out. Returns {"wavelengths_m", "lsr", "left_out_m"}."""
    kept, dropped = curve_wavelengths(system.spec, extra=extra)
    lo, hi = (w * 1e-6 for w in material.valid_um)
    dropped = tuple(sorted((*dropped, *(w for w in kept if not lo <= w <= hi))))
    kept = tuple(w for w in kept if lo <= w <= hi)
    lines = LaserLines(system, material.index, kept)
    rows = lines.table_of_phases(phases_of(lines), cell_m)
    return {"wavelengths_m": [r["wavelength_m"] for r in rows], "lsr": [r["lsr"] for r in rows],
            "left_out_m": list(dropped)}


def lsr_wavelength_figure(curves: dict[str, dict], design_m: float, marked: tuple, title: str):
    """LSR against wavelength, one curve per entry of ``curves`` (lsr_curve's dicts), log scale; the design
    wavelength and the ``marked`` laser lines as vertical lines, the range a curve could not hold shaded."""
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    for name, c in curves.items():
        ax.semilogy(np.array(c["wavelengths_m"]) * 1e9, c["lsr"], marker=".", label=name)
    for w in sorted(set(marked) | set(COMMON_LINES_M)):
        ax.axvline(w * 1e9, color="0.8" if w not in marked else "tab:red", lw=0.8, zorder=0)
    ax.axvline(design_m * 1e9, color="k", ls="--", lw=1, label=f"design wavelength {design_m * 1e9:.0f} nm")
    left = sorted({w for c in curves.values() for w in c["left_out_m"]})
    if left:
        for w in left:
            ax.axvspan(w * 1e9 - 5, w * 1e9 + 5, color="0.9", lw=0)
        ax.fill_between([], [], color="0.9", label="not computed: the window would alias, or the material's fit "
                        "ends")
    ax.plot([], [], color="tab:red", lw=0.8, label="configured laser lines")
    ax.plot([], [], color="0.8", lw=0.8, label="common lines (405, 450, 520, 532, 633, 1064 nm)")
    ax.set_xlabel("laser wavelength [nm]")
    ax.set_ylabel("LSR (certified continuous peak / uncoded peak)")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig
