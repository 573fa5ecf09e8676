"""PSF kernels on the simulation grid: pixel-integrated, resampled at any pitch and sub-pixel offset, exactly.

The intensity PSF on the optics window is band-limited (incoherent cutoff W_a / (lambda f), below the window's
Nyquist by the optics guardrail), so its continuous form is known from its samples. The energy that a pixel of
side P centred at X collects is

    E(X) = (P / (M dx))^2 sum_j H(nu_j) S(nu_j) exp(2 pi i nu_j X),   S = sinc(nu_x P) sinc(nu_y P),

with H the DFT of the window PSF (M samples at pitch dx) and S = 1 for point sampling. The window is zero-padded
first (``padded_size``): the DFT treats its input as periodic, and without the padding a kernel wider than the
window would collect the PSF's opposite side a second time. Evaluated as two small complex matrix products, this places
a PSF at any sub-pixel position (the laser's focal offset f * n_l) and bins it to any pixel size without
wrap-around or interpolation error.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from codesign.optics.propagation import next_fast_len


def _sinc(x: torch.Tensor) -> torch.Tensor:
    return torch.special.sinc(x)  # sin(pi x) / (pi x)


def padded_size(m: int, dx: float, reach_m: float) -> int:
    """Smallest fast DFT size whose periodic PSF copies stay beyond ``reach_m`` (the farthest pixel edge) [m].

    The DFT treats the window PSF (m samples) as periodic with period size * dx; a copy occupies
    [size dx - m dx / 2, ...], so size >= reach / dx + m / 2 keeps every output pixel clear of it.
    """
    return next_fast_len(max(m, math.ceil(reach_m / dx + m / 2) + 1))


def psf_spectrum(psf: torch.Tensor, size: int) -> torch.Tensor:
    """DFT of the window PSF zero-padded to size x size, axis kept at index size // 2 (see padded_size)."""
    m0 = psf.shape[-1]
    lo = size // 2 - m0 // 2
    padded = F.pad(psf, (lo, size - m0 - lo, lo, size - m0 - lo))
    return torch.fft.fft2(torch.fft.ifftshift(padded, dim=(-2, -1)))


def resample_spectrum(h: torch.Tensor, dx: float, ys: torch.Tensor, xs: torch.Tensor, pixel_m: float,
                      integrate: bool = True) -> torch.Tensor:
    """Energy per output pixel from a PSF spectrum ``h`` (psf_spectrum), at pixel centres (ys, xs) [m].

    ys, xs may carry a leading batch dimension (L, n): then the result is (L, n_y, n_x), one footprint each.
    """
    m = h.shape[-1]
    cdtype = h.dtype
    nu = torch.fft.fftfreq(m, d=dx, dtype=torch.float64, device=h.device)
    if integrate:
        sc = _sinc(nu * pixel_m)
        h = h * (sc[:, None] * sc[None, :]).to(cdtype)

    def mat(coords: torch.Tensor) -> torch.Tensor:
        arg = 2 * math.pi * coords.to(torch.float64)[..., :, None] * nu
        return torch.polar(torch.ones_like(arg), arg).to(cdtype)

    out = mat(ys) @ h @ mat(xs).transpose(-1, -2)
    return out.real * (pixel_m / (m * dx)) ** 2


def resample_psf(psf: torch.Tensor, dx: float, ys: torch.Tensor, xs: torch.Tensor, pixel_m: float,
                 integrate: bool = True) -> torch.Tensor:
    """Energy per output pixel of a window PSF, at output pixel centres (ys, xs) relative to the PSF's axis.

    Args:
        psf: (M, M) energy fraction per window sample, axis at index M // 2, pitch ``dx`` [m].
        ys, xs: (n_y,), (n_x,) output pixel-centre coordinates [m], relative to the PSF axis.
        pixel_m: output pixel side P [m]; integrate: box-integrate over P x P (else point-sample, times P^2).
    Returns:
        (n_y, n_x) energy fractions, real, in psf's dtype (computed in that precision).
    """
    reach = float(torch.cat([ys.abs(), xs.abs()]).max()) + pixel_m / 2 if ys.numel() else pixel_m
    size = padded_size(psf.shape[-1], dx, reach)
    cdtype = torch.complex128 if psf.dtype == torch.float64 else torch.complex64
    return resample_spectrum(psf_spectrum(psf, size).to(cdtype), dx, ys, xs, pixel_m, integrate)


def symmetric_coords(n: int, pitch: float, device=None) -> torch.Tensor:
    """Pixel-centre coordinates (i - (n - 1) / 2) * pitch [m], symmetric about the axis (for even n no pixel lies
    on it). Compare optics.grid.axis_coords, which always puts sample n // 2 on the axis."""
    return (torch.arange(n, dtype=torch.float64, device=device) - (n - 1) / 2) * pitch


def conserve_energy(patch: torch.Tensor, psf: torch.Tensor) -> torch.Tensor:
    """Rescale a resampled footprint so that it holds exactly the window PSF's energy.

    The window PSF is truncated at the window edge, hence not strictly band-limited; its Fourier interpolant
    rings slightly beyond the window (0.15% of the energy for an uncoded PSF on a 33-sample window). The kernel
    is by definition the window's energy redistributed onto pixels, so the ringing is folded back.
    """
    return patch * (psf.sum() / patch.sum())


def kernel(psf: torch.Tensor, dx: float, size: int, pitch: float, integrate: bool = True,
           spectrum: torch.Tensor | None = None) -> torch.Tensor:
    """Odd-sized (size x size) PSF kernel at ``pitch``, centred on the axis (index size // 2), energy sum(psf).

    ``spectrum``: a psf_spectrum of ``psf`` to resample from (default: one padded just enough for this kernel).
    """
    c = symmetric_coords(size, pitch, psf.device)
    k = resample_psf(psf, dx, c, c, pitch, integrate) if spectrum is None else \
        resample_spectrum(spectrum, dx, c, c, pitch, integrate)
    return conserve_energy(k, psf)


def kernel_otf(k: torch.Tensor, n_fft: int | tuple[int, int]) -> torch.Tensor:
    """rfft2 of an odd (..., k, k) kernel wrapped so its centre sits at index 0, on an n_fft x n_fft grid (or
    (rows, columns) for a rectangular one)."""
    rows, cols = (n_fft, n_fft) if isinstance(n_fft, int) else n_fft
    size = k.shape[-1]
    c = size // 2
    padded = k.new_zeros(k.shape[:-2] + (rows, cols))
    padded[..., :size, :size] = k
    padded = torch.roll(padded, shifts=(-c, -c), dims=(-2, -1))
    return torch.fft.rfft2(padded)


def otf_from_kernel(kernel: torch.Tensor, size: int | tuple[int, int]) -> torch.Tensor:
    """rfft2 (size x size // 2 + 1, or rows x columns // 2 + 1 for ``size`` = (rows, columns)) of a centred (k, k)
    PSF kernel zero-padded to that grid, its centre moved to pixel (0, 0) so that filtering does not shift the
    image. H(0) = sum(kernel)."""
    k = kernel.shape[-1]
    if k > min((size, size) if isinstance(size, int) else size):
        raise ValueError(f"kernel ({k} px) larger than the deconvolution grid ({size} px)")
    otf = kernel_otf(kernel.to(torch.float64), size)  # the simulator's own convention (same centring)
    return otf.to(torch.complex128 if kernel.dtype == torch.float64 else torch.complex64)


def convolve_valid(scene: torch.Tensor, otf: torch.Tensor, n_fft: int, ksize: int) -> torch.Tensor:
    """Linear convolution of (B, 1, S, S) scenes with a kernel given by its OTF; returns the valid (S-K+1)^2 part.

    Circular convolution on n_fft >= S samples is exact on the valid region (wrap-around only reaches the first
    K - 1 outputs), so no extra padding is needed.
    """
    s = scene.shape[-1]
    c = ksize // 2
    f = torch.fft.rfft2(scene, s=(n_fft, n_fft))
    out = torch.fft.irfft2(f * otf, s=(n_fft, n_fft))
    return out[..., c: s - c, c: s - c]
