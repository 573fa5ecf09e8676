"""The laser's light beyond the optics window, on any sensor pixel grid, at any spot position.

The simulator places the window PSF at the laser's focal offset by exact Fourier interpolation (its footprint).
``LaserHalo`` adds everything else: the far PSF (codesign/optics/far_field.py) with the window's square cut out,
as a shape of unit energy that the simulator scales by 1 - the window PSF's energy, so that window + halo hold
exactly the whole energy (the window PSF and the far PSF come from different pupil samplings and differ by ~1.6 %
in their split for the published mask).

Placing it: the energy a pixel [y0, y1] x [x0, x1] receives is a box integral of the halo, i.e. four values of its
integral image C (cumulative sums of the far samples, float64). The far samples are cells of uniform irradiance,
so C is bilinear between cell edges and the box integral is exact for any pixel pitch and any sub-pixel spot
position: one grid_sample of C at the (n + 1)^2 pixel edges per laser. Light beyond the far plane (+-reach from
the spot) is left out.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F


class LaserHalo:
    """The far PSF outside the window square, normalized to unit energy, ready to be integrated over pixels (the
    simulator scales it by the energy the window PSF leaves out, 1 - sum(window PSF)).

    Args:
        far: (L, L) unit-energy far PSF (energy per sample), axis at index L // 2; pitch: its sample side [m];
        window_m: (lo, hi) edges of the window square around the axis [m] (what the footprint already holds).
    """

    def __init__(self, far: torch.Tensor, pitch: float, window_m: tuple[float, float]):
        far = far.detach().to(torch.float64)
        n = far.shape[-1]
        self.pitch, self.n = float(pitch), n
        centres = (torch.arange(n, dtype=torch.float64, device=far.device) - n // 2) * pitch
        inside = (centres >= window_m[0]) & (centres < window_m[1])
        halo = torch.where(inside[:, None] & inside[None, :], torch.zeros_like(far), far)
        raw = float(halo.sum())
        self.far_energy = raw  # the far PSF's own energy outside the window square (before normalizing)
        halo = halo / raw if raw > 0 else halo
        # C[i, j]: energy of the cells above-left of edge (i, j); edge i sits at (i - n // 2 - 1/2) * pitch
        c = torch.zeros(n + 1, n + 1, dtype=torch.float64, device=far.device)
        c[1:, 1:] = halo.cumsum(0).cumsum(1)
        self.integral = c[None, None]

    def _edges(self, centre_m: float, n: int, pitch_m: float) -> torch.Tensor:
        """Normalized grid_sample coordinates of the n + 1 pixel edges of a centred grid of n pixels of side
        ``pitch_m``, relative to a spot at ``centre_m``."""
        edges = (torch.arange(n + 1, dtype=torch.float64, device=self.integral.device) - n / 2) * pitch_m
        index = (edges - centre_m) / self.pitch + self.n // 2 + 0.5
        return index * 2 / self.n - 1  # align_corners=True over the n + 1 edges of C

    def pixel_energy(self, spot_yx_m: tuple[float, float], n: int, pitch_m: float) -> torch.Tensor:
        """(n, n) float64: the fraction of the halo's energy each pixel of a centred n x n grid of pitch
        ``pitch_m`` receives from a laser whose spot sits at ``spot_yx_m`` = (y, x) [m] from the grid's centre."""
        gy = self._edges(float(spot_yx_m[0]), n, pitch_m)
        gx = self._edges(float(spot_yx_m[1]), n, pitch_m)
        yy, xx = torch.meshgrid(gy, gx, indexing="ij")
        grid = torch.stack([xx, yy], -1)[None]  # grid_sample takes (x, y)
        c = F.grid_sample(self.integral, grid, mode="bilinear", padding_mode="border", align_corners=True)[0, 0]
        # differences of a cumulative sum: an empty pixel may come out as -1e-17, which is not light
        return (c[1:, 1:] - c[:-1, 1:] - c[1:, :-1] + c[:-1, :-1]).clamp_min(0)
