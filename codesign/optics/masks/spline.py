"""The smooth freeform phase: a cubic B-spline surface on a square grid of control values.

    phi(u, v) = sum_{k, l} C[k, l] beta((v - c_k) / s) beta((u - c_l) / s),   c_k = k s (k = -K..K), s = control pitch

with beta the cubic B-spline. The surface is defined at every point of the pupil, so on another pupil grid (a finer
one, to check that the design grid resolves it) it is evaluated exactly, not interpolated; cubic B-splines
reproduce polynomials up to degree 3, so a defocus start is exact. With the control pitch at twice the pupil pitch
the surface varies on a scale the pupil grid samples twice: the design stays resolved, where a phase per pupil
sample (the pixel family) learns structure between samples that a finer grid does not reproduce (docs/codesign.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import torch

from codesign.errors import ConfigError, require_choice, require_number
from codesign.optics.grid import PupilGrid
from codesign.optics.masks.base import NAMED_STARTS, Mask, PhaseFitSpec, fill_outside, require_phases
from codesign.optics.masks.starts import named_start


@dataclass(frozen=True)
class SplineSpec(PhaseFitSpec):
    """control_spacing: control pitch in pupil samples of the grid the mask is built on (2: the surface varies on
    twice the sampling pitch); init: defocus (phi = defocus_rad (rho / R)^2, exact), published (least-squares fit of
    the published half-ring phase under init_convention), zero, or the path of a mask record (any family: fitted;
    a spline record of the same control grid: its values)."""

    kind: str = "spline"
    init: str | None = "defocus"
    control_spacing: float = 2.0


def cubic_bspline(t: torch.Tensor) -> torch.Tensor:
    """The centred cubic B-spline beta(t), support |t| < 2, sum over integer shifts = 1."""
    a = t.abs()
    return torch.where(a < 1, 2 / 3 - a**2 + a**3 / 2, torch.where(a < 2, (2 - a) ** 3 / 6, torch.zeros_like(a)))


def basis(coords: torch.Tensor, pitch: float, half: int) -> torch.Tensor:
    """B[i, k] = beta(coords_i / pitch - (k - half)), shape (len(coords), 2 half + 1), float64."""
    k = torch.arange(-half, half + 1, dtype=torch.float64, device=coords.device)
    return cubic_bspline(coords.to(torch.float64)[:, None] / pitch - k[None, :])


def control_half(support_radius_m: float, control_pitch_m: float) -> int:
    """K such that controls -K..K cover a support of this radius plus the cubic spline's reach (2 pitches)."""
    return int(math.ceil(support_radius_m / control_pitch_m)) + 2


def check_control_grid(control_pitch_m, half, prefix: str) -> tuple[float, int]:
    """The control pitch [m] (> 0, at most 10 m: an aperture's bound) and K (an integer in [1, 100000])."""
    return (require_number(f"{prefix}.control_pitch_m", control_pitch_m, lo=0, lo_open=True, hi=10),
            require_number(f"{prefix}.control_half", half, lo=1, hi=100000, integer=True))


class SplineMask(Mask):
    """Learnable control values ``controls`` (2K+1, 2K+1) [rad] at pitch ``control_pitch_m`` [m], centred on the
    axis (``half`` = K; control_half gives the K that covers an aperture)."""

    kind = "spline"
    record_values = {"controls": "list", "control_pitch_m": "number", "control_half": "number"}
    Spec = SplineSpec
    fits_phases = True
    search_start = "defocus"
    # rad: at 2 samples per control pitch the surface can still turn faster than the grid samples it (a 2400-eval
    # search found steps up to pi and an LSR 6 % higher on a grid twice as fine); the cap keeps it resolved
    resolution_step = 1.0

    def __init__(self, grid: PupilGrid, control_pitch_m: float, half: int, controls: torch.Tensor | None = None,
                 levels: int | None = None, prefix: str = "mask"):
        super().__init__(grid, levels)
        self.control_pitch_m, self.half = check_control_grid(control_pitch_m, half, prefix)
        b = basis(grid.u, control_pitch_m, self.half)
        self.register_buffer("b", b.to(grid.rho.dtype), persistent=False)
        size = 2 * self.half + 1
        c = torch.zeros(size, size, dtype=grid.rho.dtype, device=grid.rho.device)
        if controls is not None:
            if tuple(controls.shape) != (size, size):
                raise ValueError(f"{prefix}.init spline controls have shape {tuple(controls.shape)}, this grid needs "
                                 f"{size} x {size}")
            c = controls.detach().to(c).clone()
        self.controls = torch.nn.Parameter(c)

    def support_phase(self) -> torch.Tensor:
        """The phase [rad] at the support samples: the bicubic B-spline surface of the control values."""
        full = self.b @ self.controls @ self.b.T  # rows v, columns u: the grid is square and shares u, v
        return full.reshape(-1)[self.grid.support]

    # ---- fitting ------------------------------------------------------------------------------------------------
    @torch.no_grad()
    def fit(self, phase: torch.Tensor, iterations: int = 500) -> None:
        """Least-squares control values for a full-grid (n, n) phase on the aperture support: the separable
        solution pinv(B) phase pinv(B)^T of the phase extended outside (nearest inside value), refined by
        conjugate gradients on the normal equations restricted to the support."""
        b = self.b.to(torch.float64)
        inside = torch.zeros(self.grid.n * self.grid.n, dtype=torch.float64, device=b.device)
        inside[self.grid.support] = 1.0
        inside = inside.reshape(self.grid.n, self.grid.n)
        target = fill_outside(phase.detach().to(torch.float64), self.grid)
        pinv = torch.linalg.pinv(b)
        c = pinv @ target @ pinv.T
        normal = lambda x: b.T @ (inside * (b @ x @ b.T)) @ b  # noqa: E731
        r = b.T @ (inside * target) @ b - normal(c)
        d, rr = r.clone(), (r * r).sum()
        for _ in range(iterations):
            if float(rr) <= 1e-28 * max(float((target**2).sum()), 1.0):
                break
            ad = normal(d)
            step = rr / (d * ad).sum()
            c, r = c + step * d, r - step * ad
            rr_new = (r * r).sum()
            d, rr = r + (rr_new / rr) * d, rr_new
        self.controls.copy_(c.to(self.controls))

    def fit_phase(self, phase: torch.Tensor) -> None:
        """Fit the control values to a full-grid (n, n) phase [rad] (least squares on the support: ``fit``)."""
        self.fit(phase)

    @torch.no_grad()
    def defocus_vector(self, strength_rad: float) -> torch.Tensor:
        """Exact in this family (set_defocus), where the base class fits the phase."""
        keep = self.to_vector()
        self.set_defocus(strength_rad, float(self.grid.rho.reshape(-1)[self.grid.support].max()))
        out = self.to_vector()
        self.set_vector(keep)
        return out

    def set_defocus(self, defocus_rad: float, radius_m: float) -> None:
        """Controls of phi = defocus_rad (rho / radius)^2, exact: sum_k beta(t - k) k^2 = t^2 + 1/3, and the
        controls of u^2 + v^2 separate (the spline's weights sum to 1 along each axis)."""
        k = torch.arange(-self.half, self.half + 1, dtype=torch.float64) * self.control_pitch_m
        q = k**2 - self.control_pitch_m**2 / 3
        with torch.no_grad():
            self.controls.copy_((defocus_rad / radius_m**2 * (q[:, None] + q[None, :])).to(self.controls))

    # ---- the family interface -------------------------------------------------------------------------------------
    def bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(lower, upper): +-1e4 rad for every control value (float64)."""
        n = self.vector_size
        return torch.full((n,), -1e4, dtype=torch.float64), torch.full((n,), 1e4, dtype=torch.float64)

    def settings(self) -> dict[str, Any]:
        """The control grid: its pitch [m] and half width (in controls)."""
        return {"control_pitch_m": self.control_pitch_m, "control_half": self.half}

    def parameter_values(self) -> dict[str, Any]:
        """The control values [rad] at 9 significant digits, JSON-ready."""
        return {"controls": [float(f"{v:.9g}") for v in self.controls.detach().reshape(-1).cpu().tolist()]}

    def on_grid(self, grid: PupilGrid, aperture_diameter_m: float) -> "SplineMask":
        """The same surface on another pupil grid, frozen."""
        return SplineMask(grid, self.control_pitch_m, self.half, self.controls.detach(), levels=self.levels).freeze()

    @classmethod
    def check_record(cls, record: Mapping[str, Any], prefix: str) -> None:
        """Check a spline record (mask.init=PATH) under ``prefix``: its control grid and values; ConfigError naming
        the key otherwise."""
        _, half = check_control_grid(record["control_pitch_m"], record["control_half"], prefix)
        controls, size = record["controls"], 2 * half + 1
        if len(controls) != size * size:
            raise ConfigError(f"{prefix}.controls", controls, f"must hold (2 control_half + 1)^2 = {size * size} "
                              f"control values (control_half = {half}), it holds {len(controls)}")
        require_phases(f"{prefix}.controls", controls)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], grid: PupilGrid, aperture_diameter_m: float,
                    start_phase: torch.Tensor | None = None, record: dict | None = None,
                    prefix: str = "mask") -> "SplineMask":
        """``record``: a spline record (the same physical surface: its control pitch and values); ``start_phase``:
        the (n, n) phase of another family's record, fitted; else ``init`` (defocus, published, zero), fitted."""
        if record is not None:
            half = int(record["control_half"])
            controls = torch.tensor(record["controls"], dtype=torch.float64).reshape(2 * half + 1, 2 * half + 1)
            return cls(grid, float(record["control_pitch_m"]), half, controls, levels=cfg.get("levels"),
                       prefix=prefix)
        spacing = require_number(f"{prefix}.control_spacing", cfg.get("control_spacing", SplineSpec.control_spacing),
                                 lo=0.5, hi=100)
        radius = float(grid.rho.reshape(-1)[grid.support].max())
        mask = cls(grid, spacing * grid.pitch, control_half(radius, spacing * grid.pitch), levels=cfg.get("levels"),
                   prefix=prefix)
        if start_phase is None:
            init = require_choice(f"{prefix}.init", cfg.get("init", SplineSpec.init), NAMED_STARTS)
            if init == "defocus":
                mask.set_defocus(require_number(f"{prefix}.defocus_rad", cfg.get("defocus_rad", SplineSpec.defocus_rad),
                                                lo=-1e4, hi=1e4), aperture_diameter_m / 2)
                return mask
            start_phase = named_start(init, grid, aperture_diameter_m, cfg, prefix)
        if start_phase is not None:
            mask.fit(start_phase)
        return mask
