"""Pupil field -> focal field: a matrix Fourier transform (MFT), a chirp-z transform and a zero-padded FFT, behind
one interface.

Both compute the Fraunhofer integral E(x, y) = sum_{u,v} P(u, v) exp(-2 pi i (x u + y v) / (lambda f)) on a
focal window centred on the axis. (Eq. 4 of the paper writes exp(+i k (x u + y v) / f); that sign only mirrors
the PSF through the axis. We use the physical sign, so a wavefront tilt exp(+i k alpha u) focuses at x = +f alpha.)

* MFT (Soummer et al. 2007): two dense matrix products straight onto any window at any pitch,
  cost ~ 8 (m n^2 + m^2 n) real flops for an n x n pupil and m x m window. torch has no MFT: written here.
* chirp-z (Bluestein): the same sums on the same window, with x_k u_j = ((x_k)^2 + (u_j)^2 - (x_k - u_j)^2) / 2
  turning each axis into chirp products and one convolution, done by FFTs of a fast length L >= n + m - 1; cost
  ~ (n + m) 2 (5 L log2 L + 6 L) real flops. Exact like the MFT (same sums), far fewer flops; GEMMs run those
  flops faster than FFTs, so ``propagator: auto`` compares the two with a measured efficiency (COST_WEIGHT).
* FFT: zero-pads the pupil to fft_n, native focal pitch lambda f / (fft_n * pupil_pitch), cost
  ~ 5 N^2 log2(N^2) flops. If the wanted pitch differs from the native one, the intensity is resampled
  bilinearly (an approximation: this is the paper's 4096-point path, kept for comparison and benchmarks).
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from codesign.optics.grid import axis_coords
from codesign.optics.spec import OpticsSpec

_FAST_RADICES = (2, 3, 5, 7)


def next_fast_len(n: int, radices: tuple[int, ...] = _FAST_RADICES) -> int:
    """Smallest integer >= n whose only prime factors are in ``radices`` (default 2, 3, 5, 7: fast for pocketfft
    and cuFFT)."""
    m = max(int(n), 1)
    while True:
        k = m
        for p in radices:
            while k % p == 0:
                k //= p
        if k == 1:
            return m
        m += 1


# How many times slower a flop runs in an FFT than in a GEMM: the modelled cost of an FFT-based propagator is its
# flop count times this weight. Measured on the propagation (phase -> PSF -> smooth LSR, forward + backward, 640
# window, 2 threads, AMD EPYC, torch 2.13 CPU, the blocked chirp-z): the MFT's flops / the chirp-z's flops over
# their time ratio is 8.2 to 11.1 from 192 to 512 samples across, float32 and float64 (median 10). The choice only
# changes speed, never the result beyond rounding. The zero-padded FFT keeps the 11 measured before the chirp-z's
# blocking (its 2-D transform is not blocked).
COST_WEIGHT = {"mft": 1.0, "czt": 10.0, "fft": 11.0}


def mft_cost(pupil_n: int, window_n: int) -> float:
    """Real flops of the separable complex MFT (each complex MAC = 8 real flops)."""
    return 8.0 * (window_n * pupil_n**2 + window_n**2 * pupil_n)


def czt_length(pupil_n: int, window_n: int) -> int:
    """The FFT length of the chirp-z convolutions: the smallest 5-smooth size that holds the n + m - 1 kernel taps.
    Radix 7 is left out: in torch's CPU FFT (MKL) a batch of 1066 rows ran 1.4-2x slower at 1715 = 5 x 7^3 than at
    1728 = 2^6 x 3^3, and 1050 = 2 x 3 x 5^2 x 7 slower than 1080 (AMD EPYC, 1 thread)."""
    return next_fast_len(pupil_n + window_n - 1, radices=(2, 3, 5))


def czt_cost(pupil_n: int, window_n: int) -> float:
    """Real flops of the separable chirp-z: n rows then m columns, each a forward and an inverse FFT of length L
    plus the chirp and kernel products."""
    n_fft = czt_length(pupil_n, window_n)
    return (pupil_n + window_n) * 2.0 * (5.0 * n_fft * math.log2(n_fft) + 6.0 * n_fft)


def fft_cost(fft_n: int) -> float:
    """Real flops of a 2-D FFT propagation on an ``fft_n`` x ``fft_n`` grid (5 N log2 N)."""
    return 5.0 * fft_n**2 * math.log2(max(fft_n**2, 2))


def modelled_costs(spec: OpticsSpec) -> dict[str, float]:
    """Weighted cost of every propagator that is exact for ``spec`` (the FFT only where an integer size gives the
    focal pitch exactly)."""
    n, m = spec.grid_n, spec.focal_n
    out = {"mft": COST_WEIGHT["mft"] * mft_cost(n, m), "czt": COST_WEIGHT["czt"] * czt_cost(n, m)}
    k = exact_fft_size(spec)
    if k is not None:
        out["fft"] = COST_WEIGHT["fft"] * fft_cost(k)
    return out


def exact_fft_size(spec: OpticsSpec) -> int | None:
    """The FFT size whose native pitch equals the focal pitch exactly (to 1e-9), if it exists and holds the pupil."""
    n = spec.lambda_f / (spec.pupil_pitch_m * spec.focal_pitch_m)
    k = round(n)
    if abs(n - k) <= 1e-9 * n and k >= max(spec.grid_n, spec.focal_n):
        return k
    return None


def default_fft_size(spec: OpticsSpec) -> int:
    """Smallest fast FFT size whose native pitch is at most half the focal pitch (and that holds the pupil)."""
    return next_fast_len(max(math.ceil(2 * spec.lambda_f / (spec.pupil_pitch_m * spec.focal_pitch_m)), spec.grid_n))


def choose_propagator(spec: OpticsSpec) -> str:
    """Resolve ``spec.propagator``: 'auto' picks the cheapest exact propagator by modelled cost (deterministic:
    the same sizes always give the same choice, so runs stay reproducible)."""
    if spec.propagator != "auto":
        return spec.propagator
    costs = modelled_costs(spec)
    return min(costs, key=costs.get)


# Rows per thread in one block of the chirp-z's FFTs on the CPU. Blocking keeps a block's FFT, kernel product and
# inverse FFT in cache, and it sidesteps a cliff of the batched CPU FFT: 1066 rows of 1728 points took 26 ms as
# one batch and 9.2 ms in blocks of 64-128 rows (complex64, 1 thread; 56 -> 18 ms in complex128; at 2 threads
# 15.5 -> 5.0 ms in blocks of 256); forward + backward is flat within 10 % from 32 to 128 rows per thread. Blocks
# change which rows share a call, never a row's arithmetic.
CZT_ROWS_PER_THREAD = 64


class ChirpZ(torch.nn.Module):
    """The 1-D transform E_k = sum_j P_j exp(-2 pi i x_k u_j / (lambda f)) on centred grids (``axis_coords``) as a
    Bluestein convolution, applied along the last two axes of a (..., n, n) field. With k' = k - m // 2,
    j' = j - n // 2 and a = dx du / (lambda f): E_k = w_k sum_j (P_j w_j) c_{k' - j'}, w_t = exp(-i pi a t^2),
    c_t = exp(+i pi a t^2); the kernel taps t = k' - j' run over n + m - 1 values (no wrap in a length-L FFT)."""

    def __init__(self, pupil_n: int, window_n: int, pupil_pitch_m: float, focal_pitch_m: float, lambda_f: float,
                 cdtype, device=None):
        super().__init__()
        n, m = pupil_n, window_n
        self.n, self.m, self.length = n, m, czt_length(n, m)
        a = pupil_pitch_m * focal_pitch_m / lambda_f

        def chirp(t: torch.Tensor, sign: float) -> torch.Tensor:
            # (a t^2 / 2) mod 1 before the 2 pi: the argument grows to ~1e3 rad, and reducing in float64 keeps the
            # chirp exact to ~1e-16 whatever the sizes
            frac = torch.remainder(0.5 * a * t.to(torch.float64) ** 2, 1.0)
            return torch.polar(torch.ones_like(frac), sign * 2 * math.pi * frac)

        j = torch.arange(n, dtype=torch.float64, device=device) - n // 2
        k = torch.arange(m, dtype=torch.float64, device=device) - m // 2
        taps = torch.arange(n + m - 1, dtype=torch.float64, device=device) + (-(m // 2) - (n - 1 - n // 2))
        kernel = torch.fft.fft(chirp(taps, +1.0), n=self.length)
        self.register_buffer("w_in", chirp(j, -1.0).to(cdtype), persistent=False)
        self.register_buffer("w_out", chirp(k, -1.0).to(cdtype), persistent=False)
        self.register_buffer("kernel", kernel.to(cdtype), persistent=False)

    def _axis(self, x: torch.Tensor) -> torch.Tensor:
        """The chirp-filtered sums along the last axis of (..., n) -> (..., m): input chirp, FFT, kernel, inverse
        FFT, in blocks of rows on the CPU (CZT_ROWS_PER_THREAD); the output chirp not applied."""
        rows = x.reshape(-1, self.n)
        block = rows.shape[0] if x.device.type != "cpu" else CZT_ROWS_PER_THREAD * torch.get_num_threads()
        lo = self.n - 1
        out = [torch.fft.ifft(torch.fft.fft(b * self.w_in, n=self.length) * self.kernel)[:, lo: lo + self.m]
               for b in rows.split(block)]
        return (out[0] if len(out) == 1 else torch.cat(out)).reshape(*x.shape[:-1], self.m)

    def forward(self, field: torch.Tensor, output_chirp: bool = True) -> torch.Tensor:
        """The focal field (..., m, m). ``output_chirp=False`` leaves out the unit-modulus factor w_k w_l of the
        output, which |E|^2 does not see (each is constant along the other axis's transform): what intensities
        need, two complex products fewer."""
        rows = self._axis(field)  # (..., n, m): along u
        out = self._axis(rows.transpose(-1, -2)).transpose(-1, -2)  # (..., m, m): then along v
        if output_chirp:
            out = out * self.w_out[:, None] * self.w_out[None, :]
        return out


def mft_matrix(out_coords: torch.Tensor, in_coords: torch.Tensor, lambda_f: float, dtype) -> torch.Tensor:
    """Kernel W[k, j] = exp(-2 pi i out_k in_j / (lambda f)), shape (len(out), len(in)), built in float64."""
    arg = (-2 * math.pi / lambda_f) * torch.outer(out_coords.to(torch.float64), in_coords.to(torch.float64))
    return torch.polar(torch.ones_like(arg), arg).to(dtype)


def mft(field: torch.Tensor, w_rows: torch.Tensor, w_cols: torch.Tensor) -> torch.Tensor:
    """E = W_rows @ P @ W_cols^T for a (..., n, n) complex field; returns (..., m_rows, m_cols)."""
    return w_rows @ field @ w_cols.transpose(-1, -2)


class Propagator(torch.nn.Module):
    """Pupil field (..., n, n) complex -> focal field on the spec's window (..., m, m), unnormalized DFT sums.

    ``intensity(field)`` returns |E|^2 normalized to a unit-energy PSF sampled at the focal pitch (energy per
    focal pixel as a fraction of the field's total energy, point-sampled irradiance times pixel area).
    """

    def __init__(self, spec: OpticsSpec, method: str | None = None, dtype=torch.float32, device=None):
        super().__init__()
        self.spec = spec
        self.method = method or choose_propagator(spec)
        self.real_dtype = dtype
        cdtype = torch.complex128 if dtype == torch.float64 else torch.complex64
        n, m = spec.grid_n, spec.focal_n
        if self.method == "mft":
            pupil = axis_coords(n, spec.pupil_pitch_m, device=device)
            focal = axis_coords(m, spec.focal_pitch_m, device=device)
            w = mft_matrix(focal, pupil, spec.lambda_f, cdtype)
            self.register_buffer("w", w, persistent=False)
            self.native_pitch = spec.focal_pitch_m
        elif self.method == "czt":
            self.czt = ChirpZ(n, m, spec.pupil_pitch_m, spec.focal_pitch_m, spec.lambda_f, cdtype, device)
            self.native_pitch = spec.focal_pitch_m
        elif self.method == "fft":
            self.fft_n = spec.fft_n or exact_fft_size(spec) or default_fft_size(spec)
            self.native_pitch = spec.lambda_f / (self.fft_n * spec.pupil_pitch_m)
            self.resample = abs(self.native_pitch / spec.focal_pitch_m - 1) > 1e-9
            if self.resample:
                native_extent = self.fft_n * self.native_pitch
                if spec.focal_extent_m > native_extent:
                    raise ValueError(f"fft_n = {self.fft_n}: its field {native_extent:.4g} m is smaller than the "
                                     f"focal window {spec.focal_extent_m:.4g} m")
                # grid_sample coordinates of the window's sample centres in the native (fftshifted) grid.
                pos = axis_coords(m, spec.focal_pitch_m, device=device) / self.native_pitch  # native samples
                norm = (pos + self.fft_n // 2) * 2 / (self.fft_n - 1) - 1  # align_corners=True
                gy, gx = torch.meshgrid(norm, norm, indexing="ij")
                self.register_buffer("sample_grid", torch.stack([gx, gy], -1)[None].to(dtype), persistent=False)
        else:
            raise ValueError(f"optics.propagator = {self.method!r}: must be one of auto, mft, czt, fft")

    def field(self, pupil_field: torch.Tensor, exact_phase: bool = True) -> torch.Tensor:
        """Focal field on the window (MFT, chirp-z), or on the full native FFT grid, fftshifted (FFT).
        ``exact_phase=False``: a field whose modulus is exact (the chirp-z leaves out a unit-modulus factor)."""
        if self.method == "mft":
            return mft(pupil_field, self.w, self.w)
        if self.method == "czt":
            return self.czt(pupil_field, output_chirp=exact_phase)
        n, big = pupil_field.shape[-1], self.fft_n
        lo = big // 2 - n // 2
        padded = F.pad(pupil_field, (lo, big - n - lo, lo, big - n - lo))
        # ifftshift puts the pupil's axis sample at index 0, fftshift puts the focal axis at big // 2.
        spec = torch.fft.fft2(torch.fft.ifftshift(padded, dim=(-2, -1)))
        return torch.fft.fftshift(spec, dim=(-2, -1))

    def intensity(self, pupil_field: torch.Tensor) -> torch.Tensor:
        """Unit-energy PSF on the focal window, shape (..., m, m), real dtype of the module."""
        s = self.spec
        # |P|^2 through the real view: a complex abs() is a hypot per sample, 10x slower at 1066^2
        energy = torch.view_as_real(pupil_field).square().sum(dim=(-3, -2, -1))[..., None, None]
        e = self.field(pupil_field, exact_phase=False)
        # Parseval: sum over the whole plane of |E|^2 (d_u d_x / (lambda f))^2 equals sum |P|^2.
        scale = (s.pupil_pitch_m * self.native_pitch / s.lambda_f) ** 2
        psf = torch.view_as_real(e).square().sum(dim=-1) * (scale / energy)
        if self.method in ("mft", "czt"):
            return psf
        m = s.focal_n
        if not self.resample:
            c = self.fft_n // 2
            return psf[..., c - m // 2: c - m // 2 + m, c - m // 2: c - m // 2 + m]
        lead = psf.shape[:-2]
        flat = psf.reshape(-1, 1, self.fft_n, self.fft_n)
        grid = self.sample_grid.expand(flat.shape[0], -1, -1, -1)
        out = F.grid_sample(flat, grid, mode="bilinear", align_corners=True)
        # Bilinear values are irradiance samples; rescale from native to focal pixel area.
        return out.reshape(*lead, m, m) * (s.focal_pitch_m / self.native_pitch) ** 2
