"""Pupil and focal sampling grids and the super-Gaussian aperture (Sec. 3.1).

Conventions: a grid of n samples at pitch d has coordinates (i - n // 2) * d, i = 0..n-1, so the optical axis is
sample n // 2 (the ``fftshift`` centre) and is always sampled exactly. Images are indexed [row, col] = [v, u] in the
pupil and [y, x] in the focal plane.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from codesign.optics.spec import OpticsSpec


def axis_coords(n: int, pitch: float, dtype=torch.float64, device=None) -> torch.Tensor:
    """Sample coordinates (i - n // 2) * pitch [m], shape (n,): sample n // 2 lies on the optical axis (the fftshift
    centre), for even and odd n. Compare sensor.kernels.symmetric_coords, whose pixel centres straddle the axis."""
    return (torch.arange(n, dtype=torch.float64, device=device) - n // 2).mul(pitch).to(dtype)


def supergaussian_aperture(rho: torch.Tensor, diameter: float, order: float) -> torch.Tensor:
    """A(rho) = exp(-(4 rho^2 / W_a^2)^order), the smooth circular aperture of Sec. 3.1 (rho, diameter in m)."""
    return torch.exp(-torch.pow(4 * rho**2 / diameter**2, order))


@dataclass
class PupilGrid:
    """Sampled pupil plane: coordinates, polar coordinates, aperture, and the support where the aperture is > 0.

    Attributes:
        n: samples per side; pitch: sample pitch [m].
        u, v: 1-D coordinates [m], shape (n,) (u along columns, v along rows).
        rho: radius sqrt(u^2 + v^2) [m], shape (n, n).
        angle: polar angle Phi [rad], shape (n, n). As printed in Sec. 3.1, Phi = atan(u / v), made
            quadrant-correct as atan2(u, v) (measured from the +v axis towards +u).
        aperture: super-Gaussian amplitude A, shape (n, n), exactly 0 outside the support.
        support: flat indices (into the n*n grid) of samples inside the aperture support, shape (n_support,).
        radius_index: for each support sample, the index of its radius in ``radii`` (exact unique radii).
        radii: the distinct radii [m] of the support samples, ascending.
    """

    n: int
    pitch: float
    u: torch.Tensor
    v: torch.Tensor
    rho: torch.Tensor
    angle: torch.Tensor
    aperture: torch.Tensor
    support: torch.Tensor
    radius_index: torch.Tensor
    radii: torch.Tensor

    @classmethod
    def from_spec(cls, spec: OpticsSpec, dtype=torch.float32, device=None) -> "PupilGrid":
        """The pupil grid of an OpticsSpec: grid_n x grid_n samples at pupil_pitch_m [m], its aperture support and
        exact distinct radii, in ``dtype`` on ``device``."""
        n, d = spec.grid_n, spec.pupil_pitch_m
        # Integer offsets make the set of distinct radii exact: rho^2 = (di^2 + dj^2) * d^2.
        k = torch.arange(n, device=device, dtype=torch.int64) - n // 2
        r2 = k[:, None] ** 2 + k[None, :] ** 2
        r2_max = (spec.aperture_support_radius_m / d) ** 2
        support = torch.nonzero(r2.reshape(-1) <= r2_max).squeeze(-1)
        uniq, inverse = torch.unique(r2.reshape(-1)[support], return_inverse=True)
        coords = k.to(torch.float64) * d
        vv, uu = torch.meshgrid(coords, coords, indexing="ij")
        rho = torch.sqrt(uu**2 + vv**2)
        aperture = supergaussian_aperture(rho, spec.aperture_diameter_m, spec.supergaussian_order)
        aperture = torch.where(r2 <= r2_max, aperture, torch.zeros_like(aperture))
        return cls(
            n=n, pitch=d,
            u=coords.to(dtype), v=coords.to(dtype),
            rho=rho.to(dtype), angle=torch.atan2(uu, vv).to(dtype),
            aperture=aperture.to(dtype),
            support=support, radius_index=inverse,
            radii=(torch.sqrt(uniq.to(torch.float64)) * d).to(dtype),
        )

    def scatter(self, values: torch.Tensor) -> torch.Tensor:
        """Place per-support-sample values (..., n_support) onto the full (..., n, n) grid, zero elsewhere."""
        out = values.new_zeros(*values.shape[:-1], self.n * self.n)
        out = out.index_copy(out.dim() - 1, self.support, values)
        return out.reshape(*values.shape[:-1], self.n, self.n)
