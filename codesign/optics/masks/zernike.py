"""The Zernike family: phase = sum_j c_j Z_j (Noll j = 1..n_terms), orthonormal on the aperture disk of radius
W_a / 2; a smooth, low-dimensional freeform phase."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import torch

from codesign.errors import ConfigError, require_choice, require_number
from codesign.optics.grid import PupilGrid
from codesign.optics.masks.base import NAMED_STARTS, Mask, PhaseFitSpec, require_phases
from codesign.optics.masks.starts import named_start


@dataclass(frozen=True)
class ZernikeSpec(PhaseFitSpec):
    """n_terms: Noll modes 1..n_terms; max_coeff_rad: the box [-max, max] of every coefficient [rad RMS]
    (project() clamps into it; the plate's depth budget); init: published | zero | defocus (the phase fitted by
    least squares) or the path of a mask record (any family: fitted); init_convention, defocus_rad: as for the
    pixel family."""

    kind: str = "zernike"
    init: str | None = "published"
    n_terms: int = 36
    max_coeff_rad: float = 50.0

    def __post_init__(self) -> None:
        super().__post_init__()
        p = self.prefix
        object.__setattr__(self, "n_terms", require_number(f"{p}.n_terms", self.n_terms, lo=1, hi=1000, integer=True))
        require_max_coeff(f"{p}.max_coeff_rad", self.max_coeff_rad)


MAX_COEFF_LIMIT = 1e4  # rad: the widest coefficients' box a config may set (the config's bound on a phase)


def require_max_coeff(key: str, value) -> float:
    """The coefficients' box [rad RMS]: > 0, at most the config's bound on a phase (MAX_COEFF_LIMIT)."""
    return require_number(key, value, lo=0, lo_open=True, hi=MAX_COEFF_LIMIT)


def noll_to_nm(j: int) -> tuple[int, int]:
    """Noll's single index j >= 1 -> (radial degree n, signed azimuthal frequency m); m < 0 is the sine term."""
    if j < 1:
        raise ValueError(f"Noll index must be >= 1, got {j}")
    n = int((math.isqrt(8 * j - 7) - 1) // 2)
    k = j - n * (n + 1) // 2 - 1  # position within degree n, from 0
    m_abs = 2 * ((k + 1) // 2) if n % 2 == 0 else 2 * (k // 2) + 1
    if m_abs == 0:
        return n, 0
    return n, (m_abs if j % 2 == 0 else -m_abs)  # Noll: even j -> cosine, odd j -> sine


def zernike(n: int, m: int, rho: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Orthonormal Zernike polynomial Z_n^m on the unit disk (rho normalized, angle [rad]), float64 inside."""
    rho64, ang64 = rho.to(torch.float64), angle.to(torch.float64)
    ma = abs(m)
    radial = torch.zeros_like(rho64)
    for k in range((n - ma) // 2 + 1):
        c = (-1) ** k * math.factorial(n - k) / (
            math.factorial(k) * math.factorial((n + ma) // 2 - k) * math.factorial((n - ma) // 2 - k))
        radial = radial + c * rho64 ** (n - 2 * k)
    if m == 0:
        z = math.sqrt(n + 1) * radial
    else:
        z = math.sqrt(2 * (n + 1)) * radial * (torch.cos(ma * ang64) if m > 0 else torch.sin(ma * ang64))
    return z.to(rho.dtype)


class ZernikeMask(Mask):
    """Phase = sum_j c_j Z_j (Noll j = 1..n_terms) over the aperture disk of radius W_a / 2; c_j in rad (RMS).

    ``project()`` clamps every coefficient into [-max_coeff_rad, max_coeff_rad] (the plate's depth budget).
    """

    kind = "zernike"
    record_values = {"coeffs": "list"}
    record_settings = ("n_terms", "max_coeff_rad")
    Spec = ZernikeSpec
    fits_phases = True
    search_start = "defocus"

    def __init__(self, grid: PupilGrid, aperture_diameter_m: float, n_terms: int = ZernikeSpec.n_terms,
                 init_coeffs: torch.Tensor | None = None, max_coeff_rad: float = ZernikeSpec.max_coeff_rad,
                 prefix: str = "mask", levels: int | None = None):
        super().__init__(grid, levels)
        self.aperture_diameter_m = aperture_diameter_m
        n_terms = require_number(f"{prefix}.n_terms", n_terms, lo=1, hi=1000, integer=True)
        self.max_coeff_rad = require_max_coeff(f"{prefix}.max_coeff_rad", max_coeff_rad)
        rho = grid.rho.reshape(-1)[grid.support] / (aperture_diameter_m / 2)
        ang = torch.atan2(grid.v[:, None].expand(grid.n, grid.n), grid.u[None, :].expand(grid.n, grid.n))
        ang = ang.reshape(-1)[grid.support]
        basis = torch.stack([zernike(*noll_to_nm(j), rho, ang) for j in range(1, n_terms + 1)], 0)
        self.register_buffer("basis", basis, persistent=False)
        c = torch.zeros(n_terms, dtype=grid.rho.dtype, device=grid.rho.device)
        if init_coeffs is not None:
            if init_coeffs.numel() != n_terms:
                raise ValueError(f"{prefix}.init_coeffs has {init_coeffs.numel()} values, n_terms = {n_terms}")
            c = init_coeffs.detach().to(c).reshape(-1).clone()
        self.coeffs = torch.nn.Parameter(c)

    def support_phase(self) -> torch.Tensor:
        """The phase [rad] at the support samples: the coefficients times the Zernike basis."""
        return self.coeffs @ self.basis

    def fit(self, phase: torch.Tensor, weight: torch.Tensor | None = None) -> None:
        """Set the coefficients to the (aperture-weighted) least-squares fit of a full-grid phase."""
        target = phase.detach().reshape(-1)[self.grid.support].to(torch.float64)
        w = (self.grid.aperture.reshape(-1)[self.grid.support] if weight is None else weight).to(torch.float64)
        b = self.basis.to(torch.float64) * w.sqrt()
        sol = torch.linalg.lstsq(b.T, target * w.sqrt()).solution
        with torch.no_grad():
            self.coeffs.copy_(sol.to(self.coeffs))

    @torch.no_grad()
    def project(self) -> None:
        """Clamp every coefficient into [-max_coeff_rad, max_coeff_rad]."""
        self.coeffs.clamp_(-self.max_coeff_rad, self.max_coeff_rad)

    def summary(self) -> dict[str, float]:
        """The coefficients as scalars: zernike_1.. [rad]."""
        return {f"zernike_{j + 1}": float(v) for j, v in enumerate(self.coeffs.detach().cpu())}

    # ---- the family interface -------------------------------------------------------------------------------------
    def fit_phase(self, phase: torch.Tensor) -> None:
        """Fit the coefficients to a full-grid (n, n) phase [rad] (aperture-weighted least squares: ``fit``)."""
        self.fit(phase)

    def bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(lower, upper): +-max_coeff_rad for every coefficient (float64)."""
        n = self.coeffs.numel()
        return (torch.full((n,), -self.max_coeff_rad, dtype=torch.float64),
                torch.full((n,), self.max_coeff_rad, dtype=torch.float64))

    def vector_names(self) -> list[str]:
        """zernike_1.., in ``to_vector`` order."""
        return [f"zernike_{j + 1}" for j in range(self.coeffs.numel())]

    def settings(self) -> dict[str, Any]:
        """The number of terms and the coefficients' bound [rad]."""
        return {"n_terms": self.coeffs.numel(), "max_coeff_rad": self.max_coeff_rad}

    def parameter_values(self) -> dict[str, Any]:
        """The coefficients [rad], JSON-ready."""
        return {"coeffs": [float(v) for v in self.coeffs.detach().cpu()]}

    def on_grid(self, grid: PupilGrid, aperture_diameter_m: float) -> "ZernikeMask":
        """The same mask on another pupil grid, frozen."""
        return ZernikeMask(grid, aperture_diameter_m, self.coeffs.numel(), self.coeffs.detach(), self.max_coeff_rad,
                           levels=self.levels).freeze()

    @classmethod
    def check_record(cls, record: Mapping[str, Any], prefix: str) -> None:
        """Check a Zernike record (mask.init=PATH) under ``prefix``: its number of terms, coefficients and bound;
        ConfigError naming the key otherwise."""
        coeffs = record["coeffs"]
        n_terms = require_number(f"{prefix}.n_terms", record.get("n_terms", len(coeffs)), lo=1, hi=1000, integer=True)
        if len(coeffs) != n_terms:
            raise ConfigError(f"{prefix}.coeffs", coeffs, f"must hold n_terms = {n_terms} coefficients, it holds "
                              f"{len(coeffs)}")
        bound, box = MAX_COEFF_LIMIT, "the widest box max_coeff_rad may set"  # a record without its own box
        if "max_coeff_rad" in record:
            bound, box = require_max_coeff(f"{prefix}.max_coeff_rad", record["max_coeff_rad"]), "its max_coeff_rad"
        require_phases(f"{prefix}.coeffs", coeffs)
        for i, c in enumerate(coeffs):  # 1e5 rad in a box of 50 was accepted: no design of the family reaches it
            if abs(c) > bound:
                raise ConfigError(f"{prefix}.coeffs[{i}]", c, f"outside the coefficients' box ({box}): must be "
                                  f">= -{bound:g} and <= {bound:g} rad")

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], grid: PupilGrid, aperture_diameter_m: float,
                    start_phase: torch.Tensor | None = None, record: dict | None = None,
                    prefix: str = "mask") -> "ZernikeMask":
        """``record``: a zernike record (its coefficients); ``start_phase``: the (n, n) phase of another family's
        record, fitted; else ``init`` (published, zero or defocus), fitted."""
        mask = cls(grid, aperture_diameter_m, n_terms=cfg.get("n_terms", ZernikeSpec.n_terms),
                   max_coeff_rad=cfg.get("max_coeff_rad", ZernikeSpec.max_coeff_rad), prefix=prefix,
                   levels=cfg.get("levels"))
        if record is not None:
            mask.set_vector(torch.tensor(record["coeffs"], dtype=torch.float64)[:mask.coeffs.numel()])
            return mask
        if start_phase is None:
            init = require_choice(f"{prefix}.init", cfg.get("init", ZernikeSpec.init), NAMED_STARTS)
            start_phase = named_start(init, grid, aperture_diameter_m, cfg, prefix)
        if start_phase is not None:
            mask.fit(start_phase)
        return mask

    @classmethod
    def from_record(cls, cfg: Mapping[str, Any], record: dict, grid: PupilGrid, aperture_diameter_m: float,
                    prefix: str = "mask") -> "ZernikeMask":
        """A zernike record: as many terms as it holds, its coefficient box."""
        cfg = {**cfg, "n_terms": len(record["coeffs"]), "max_coeff_rad": record.get("max_coeff_rad",
                                                                                   cfg.get("max_coeff_rad"))}
        return cls.from_config(cfg, grid, aperture_diameter_m, record=record, prefix=prefix)
