"""The continuous peak of a PSF on its focal window: a search that cannot miss a maximum between focal samples.

The PSF's irradiance I(x) = |E(x)|^2 is a band-limited function: E is the Fourier sum of pupil samples u_j, so I
holds only the frequencies (u_j - u_k) / (lambda f), of modulus at most nu = 2 r_max / (lambda f) with r_max the
largest radius of a pupil sample the aperture transmits (a plate's cell envelope sinc^2(c x / (lambda f)) adds
c / (lambda f)). Bernstein's inequality bounds every second directional derivative by (2 pi nu)^2 max I, and at the
maximum x* the gradient vanishes, so a sample s within h / sqrt(2) of x* (the centre of the h-wide square cell that
holds x*) reads at least

    I(s) >= I(x*) (1 - pi^2 (h nu)^2) = I(x*) (1 - c(h)).

The search therefore starts from a grid of cell centres that tiles the window (pitch h0 = dx / 2, every focal
sample among the centres), keeps every cell whose centre reads at least (1 - c) times the best value found so far
(the cell holding x* is always kept), splits the kept cells 3 x 3 (the centre stays a centre: the best value never
drops below the samples') and evaluates the children exactly (an MFT onto their centres), until c(h) is below
``rel_tol`` (default 3e-3: three levels on the default optics), then refines the best cell alone three levels
further. The best sample found is a lower bound of the peak and best / (1 - c) an upper bound: the peak is
certified to ``rel_tol`` whatever the PSF's shape (plateaus, ridges between rows, many equal maxima); a PSF with a
continuum of maxima (more than MAX_CELLS cells kept) stops at the level it reached, its bound wider. The bound
takes the window's maximum as the function's maximum, true for a window that holds the PSF (the window-energy check
reports the others).

Cost: the first level is one MFT onto (2m + 1)^2 points; each further level costs the distinct rows of its kept
cells times n^2, plus their distinct columns times n^2 and 9 products per kept cell (as one GEMM over every row and
column pair when that is not much more). Cell centres sit at integer multiples of the level's pitch (the optical axis
is a centre at every level).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from codesign.optics.propagation import mft_matrix

SPLIT = 3  # children per cell side at each refinement level (odd: a cell's centre is one of its children's)
FIRST_OVERSAMPLE = 2  # first-level cells per focal sample side
MAX_CELLS = 400_000  # kept cells per level above which the search stops refining (a continuum of maxima)
POLISH_LEVELS = 3  # finer levels around the best cell alone, after the certified ones
ROW_CHUNK = 256  # output rows per dense MFT block at the first level (bounds the memory)
CELL_CHUNK = 4096  # kept cells per batched product at the refinement levels
DENSE_RATIO = 16  # evaluate every (row, column) pair of the kept cells when they are at most this many per cell


@dataclass(frozen=True)
class Peak:
    """value: the continuous peak in the PSF's per-pixel units (a lower bound: the best sample found); bound: an
    upper bound (the last certified level's best / (1 - c)); y, x: its position [m]; levels, cells: the certified
    levels run and the cells evaluated."""
    value: float
    bound: float
    y: float
    x: float
    levels: int
    cells: int


def bandwidth(aperture: torch.Tensor, pupil_pitch_m: float, lambda_f: float, cell_m: float | None = None) -> float:
    """nu [1/m]: the largest spatial frequency of the irradiance of a field on this sampled aperture (see module)."""
    n = aperture.shape[-1]
    k = torch.arange(n, dtype=torch.float64, device=aperture.device) - n // 2
    r2 = k[:, None] ** 2 + k[None, :] ** 2
    r_max = float(torch.sqrt(r2[aperture.detach() != 0].max().to(torch.float64))) * pupil_pitch_m
    return (2 * r_max + (cell_m or 0.0)) / lambda_f


def shortfall(pitch: float, nu: float) -> float:
    """c(h) = pi^2 (h nu)^2: the largest relative amount a cell centre can read below a maximum in its cell."""
    return (math.pi * pitch * nu) ** 2


class PeakSearch:
    """The certified search on one system's window; ``__call__(field, cell_m)`` returns a ``Peak``.

    Args:
        pupil: pupil coordinates [m] (n,), the field's sample positions along each axis.
        lambda_f: wavelength x focal length [m^2]; focal_pitch: dx [m]; focal_n: m, window samples per side.
        aperture: the (n, n) aperture amplitude (its support sets the bandwidth); pupil_pitch: its sample pitch [m].
    """

    def __init__(self, pupil: torch.Tensor, lambda_f: float, focal_pitch: float, focal_n: int,
                 aperture: torch.Tensor, pupil_pitch: float):
        self.pupil = pupil.to(torch.float64)
        self.lambda_f, self.dx, self.m = lambda_f, focal_pitch, focal_n
        self.pupil_pitch = pupil_pitch
        self.nu = bandwidth(aperture, pupil_pitch, lambda_f)  # the aperture is fixed: a plate cell adds c / (lambda f)
        # The first level's centres, in its pitch dx / FIRST_OVERSAMPLE: from half a pixel before the first focal
        # sample ((0 - m // 2) dx) to half a pixel after the last, so that the cells cover the m pixels' squares.
        q = FIRST_OVERSAMPLE
        self.first = torch.arange(-q * (focal_n // 2) - q // 2, q * (focal_n - 1 - focal_n // 2) + q // 2 + 1)

    @staticmethod
    def centres(index: torch.Tensor, pitch: float) -> torch.Tensor:
        """Coordinates [m] of cell centres ``index`` on the level of this pitch."""
        return index.to(torch.float64) * pitch

    def __call__(self, field: torch.Tensor, cell_m: float | None = None, rel_tol: float = 3e-3) -> Peak:
        if not 0 < rel_tol < 0.1:
            raise ValueError(f"rel_tol must lie in (0, 0.1), got {rel_tol!r}")
        field = field.detach().to(torch.complex128)
        scale = ((self.pupil_pitch * self.dx / self.lambda_f) ** 2 / float(field.abs().square().sum()))
        nu = self.nu + (cell_m or 0.0) / self.lambda_f
        pitch = self.dx / FIRST_OVERSAMPLE
        first = self.first.to(field.device)
        values = self._dense(field, pitch, cell_m) * scale
        cells = torch.stack(torch.meshgrid(first, first, indexing="ij"), -1).reshape(-1, 2)
        values = values.reshape(-1)
        best, at, at_pitch = float(values.max()), cells[int(values.argmax())], pitch
        count, levels = values.numel(), 1
        while shortfall(pitch, nu) > rel_tol:
            kept = cells[values >= best * (1 - shortfall(pitch, nu))]
            if kept.shape[0] > MAX_CELLS:  # a continuum of maxima: certified only to this level's shortfall
                break
            pitch /= SPLIT
            cells, values = self._children(field, kept, pitch, cell_m)
            values = values * scale
            count, levels = count + values.numel(), levels + 1
            if float(values.max()) > best:
                best, at, at_pitch = float(values.max()), cells[int(values.argmax())], pitch
        bound = best / (1 - shortfall(pitch, nu))
        polish = at_pitch
        for _ in range(POLISH_LEVELS):  # the best cell alone, finer: a closer lower bound (the bound stands)
            polish /= SPLIT
            around, vals = self._children(field, at[None], polish, cell_m)
            vals = vals * scale
            count += vals.numel()
            if float(vals.max()) > best:
                best = float(vals.max())
            at = around[int(vals.argmax())]
        y, x = (float(v) for v in self.centres(at, polish))
        return Peak(value=best, bound=max(bound, best), y=y, x=x, levels=levels, cells=count)

    def _envelope(self, coords: torch.Tensor, cell_m: float | None) -> torch.Tensor | None:
        return None if cell_m is None else torch.sinc(coords * (cell_m / self.lambda_f)) ** 2

    def _dense(self, field: torch.Tensor, pitch: float, cell_m: float | None) -> torch.Tensor:
        """|E|^2 on every cell centre of the first level, (k, k) with k = 2 m + 1, in blocks of rows."""
        coords = self.centres(self.first.to(field.device), pitch)
        k = coords.numel()
        w = mft_matrix(coords, self.pupil, self.lambda_f, field.dtype)
        right = field @ w.transpose(0, 1)  # (n, k): along u first, shared by every block of rows
        env = self._envelope(coords, cell_m)
        out = torch.cat([(w[i:i + ROW_CHUNK] @ right).abs().square() for i in range(0, k, ROW_CHUNK)])
        return out if env is None else out * env[:, None] * env[None, :]

    def _children(self, field: torch.Tensor, parents: torch.Tensor, pitch: float, cell_m: float | None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
        """The SPLIT x SPLIT children of the cells ``parents`` (p, 2) on the level of ``pitch``: their indices
        (p * SPLIT^2, 2) and |E|^2 at their centres. Each distinct row's product with the field and each distinct
        column's kernel are made once; then one small matrix product per parent (its children share SPLIT rows
        and SPLIT columns), or one GEMM over every (row, column) pair when that is not much more work."""
        j = torch.arange(SPLIT, device=parents.device) - SPLIT // 2
        rows_of, cols_of = parents[:, :1] * SPLIT + j, parents[:, 1:] * SPLIT + j  # (p, SPLIT) each
        rows, row_at = torch.unique(rows_of, return_inverse=True)
        cols, col_at = torch.unique(cols_of, return_inverse=True)
        y, x = self.centres(rows, pitch), self.centres(cols, pitch)
        left = mft_matrix(y, self.pupil, self.lambda_f, field.dtype) @ field  # (distinct rows, n)
        right = mft_matrix(x, self.pupil, self.lambda_f, field.dtype)  # (distinct columns, n)
        if rows.numel() * cols.numel() <= DENSE_RATIO * parents.shape[0] * SPLIT**2:
            # a GEMM over every (row, column) pair runs ~20x faster per product than the per-parent products
            full = left @ right.transpose(0, 1)
            vals = full[row_at[:, :, None], col_at[:, None, :]]
        else:
            vals = torch.cat([torch.bmm(left[row_at[lo:lo + CELL_CHUNK]],
                                        right[col_at[lo:lo + CELL_CHUNK]].transpose(1, 2))
                              for lo in range(0, parents.shape[0], CELL_CHUNK)])
        vals = vals.abs().square()
        if cell_m is not None:
            vals = vals * self._envelope(y, cell_m)[row_at][:, :, None] * self._envelope(x, cell_m)[col_at][:, None, :]
        index = torch.stack(torch.broadcast_tensors(rows_of[:, :, None], cols_of[:, None, :]), -1)
        return index.reshape(-1, 2), vals.reshape(-1)
