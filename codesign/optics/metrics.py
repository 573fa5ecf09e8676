"""Figures of merit of a PSF: LSR (hard and smooth), BSR, OTF/MTF and their summaries. All differentiable.

LSR = peak(h) / peak(h0), both unit-energy PSFs of the same aperture. The uncoded peak h0(0) is taken exactly on
the optical axis (the focal grid always has a sample there, and E0(0) = sum A needs no propagation), so a grid
that misses the Airy centre cannot bias it. The hard LSR uses the coded PSF's continuous peak (certified between
samples, see ``codesign.optics.peak``); ``lsr_sampled`` is the max over the samples; ``lsr_smooth`` is a
p-norm surrogate of the max (always >= lsr_sampled) for gradient-based optimization.

BSR: a uniform background that fills the focal window gives, at the window centre, the irradiance sum(h) over the
window; BSR = sum_window(h) / sum_window(h0). It is 1 for a scene much larger than the PSF (a phase-only mask
transmits all energy) and drops below 1 when the coded PSF spreads energy beyond the window.

OTF = FFT of the PSF on the window, normalized to 1 at zero frequency; MTF = |OTF|; frequencies are normalized
to the incoherent cutoff W_a / (lambda f). The radial MTF is the mean of the 2-D MTF over rings one frequency
bin (1 / (m dx)) wide.
"""
from __future__ import annotations

import math

import torch

from codesign.errors import ConfigError
from codesign.optics.spec import OpticsSpec


def lsr_sampled(psf: torch.Tensor, uncoded_peak: float) -> torch.Tensor:
    """max over samples of h / h0(0); shape (...) for psf (..., m, m)."""
    return psf.amax(dim=(-2, -1)) / uncoded_peak


def lsr_smooth(psf: torch.Tensor, uncoded_peak: float, p: float) -> torch.Tensor:
    """Differentiable LSR surrogate ||h||_p / h0(0) >= max(h) / h0(0); -> lsr_sampled as p -> inf.

    Computed as m ||h / m||_p with m = max(h) (no gradient through m's choice, the value is exact), which keeps
    h^p within floating-point range in float32.
    """
    m = psf.detach().amax(dim=(-2, -1), keepdim=True).clamp_min(torch.finfo(psf.dtype).tiny)
    ratio = (psf / m).clamp_min(0)
    norm = ratio.pow(p).sum(dim=(-2, -1)).pow(1.0 / p)
    return norm * m.squeeze(-1).squeeze(-1) / uncoded_peak


def bsr(psf: torch.Tensor, uncoded_psf: torch.Tensor) -> torch.Tensor:
    """Background suppression ratio for a window-filling uniform scene (see module docstring)."""
    return psf.sum(dim=(-2, -1)) / uncoded_psf.sum(dim=(-2, -1))


def otf(psf: torch.Tensor) -> torch.Tensor:
    """Optical transfer function (..., m, m), complex, DC at index [0, 0], normalized to OTF(0) = 1."""
    spec = torch.fft.fft2(torch.fft.ifftshift(psf, dim=(-2, -1)))
    return spec / spec[..., :1, :1].real


def mtf(psf: torch.Tensor) -> torch.Tensor:
    """2-D modulation transfer function |OTF|, (..., m, m), DC at [0, 0]."""
    o = otf(psf)
    # |z| has an infinite gradient at z = 0; the tiny floor keeps exact OTF zeros differentiable.
    return torch.sqrt(o.real**2 + o.imag**2 + torch.finfo(psf.dtype).tiny)


class RadialMTF(torch.nn.Module):
    """Radial mean of a 2-D MTF on the spec's focal window, and its band summaries.

    Attributes:
        freqs: bin centres in normalized frequency nu / nu_c (nu_c = W_a / (lambda f)), shape (n_bins,).
    """

    def __init__(self, spec: OpticsSpec, device=None):
        super().__init__()
        m, dx = spec.focal_n, spec.focal_pitch_m
        f = torch.fft.fftfreq(m, d=dx, dtype=torch.float64, device=device)
        fr = torch.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
        step = 1.0 / (m * dx)
        idx = torch.round(fr / step).long().reshape(-1)
        n_bins = int(idx.max()) + 1
        counts = torch.bincount(idx, minlength=n_bins).to(torch.float64)
        self.register_buffer("bin_index", idx, persistent=False)
        self.register_buffer("counts", counts, persistent=False)
        self.register_buffer("freqs", torch.arange(n_bins, dtype=torch.float64, device=device) * step
                             / spec.cutoff_frequency, persistent=False)

    def forward(self, mtf2d: torch.Tensor) -> torch.Tensor:
        """Radial mean (..., n_bins) of a (..., m, m) MTF with DC at [0, 0]."""
        lead = mtf2d.shape[:-2]
        flat = mtf2d.reshape(-1, mtf2d.shape[-1] * mtf2d.shape[-2])
        out = flat.new_zeros(flat.shape[0], self.counts.numel())
        out = out.index_add(1, self.bin_index, flat)
        return (out / self.counts.to(flat.dtype)).reshape(*lead, -1)

    def band_mask(self, band: tuple[float, float]) -> torch.Tensor:
        """Bins whose centre lies in (band[0], band[1]] of normalized frequency (DC excluded)."""
        lo, hi = band
        return (self.freqs > lo) & (self.freqs <= hi) & (self.freqs > 0)

    def summary(self, radial: torch.Tensor, band: tuple[float, float]) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean, min) of the radial MTF over the band; differentiable."""
        sel = radial[..., self.band_mask(band)]
        return sel.mean(-1), sel.amin(-1)


def circular_mtf(nu: torch.Tensor) -> torch.Tensor:
    """Analytic diffraction-limited MTF of a circular pupil at normalized frequency nu = f / cutoff."""
    x = nu.clamp(0, 1)
    return (2 / torch.pi) * (torch.acos(x) - x * torch.sqrt(1 - x**2))


MAX_FOCAL_N = 16384  # OpticsSpec's bound on optics.focal_n


def require_band_frequencies(spec, band, key: str = "metrics.mtf_band") -> None:
    """ConfigError unless the MTF band holds at least one radial frequency bin of ``spec``'s window (RadialMTF's
    bins, k / (m dx), in units of the cutoff W_a / (lambda f)): a window narrower than about lambda f / W_a / high
    has none, and every mtf_mean would be the mean of nothing (it ended in "IndexError: amin(): Expected reduction
    dim -1 to have non-zero size" for optics.wavelength_m=1e-4)."""
    m, dx = spec.focal_n, spec.focal_pitch_m
    lo, hi = band
    step = 1.0 / (m * dx)
    freqs = torch.arange(round(math.sqrt(2) * (m // 2)) + 1, dtype=torch.float64) * step / spec.cutoff_frequency
    if ((freqs > lo) & (freqs <= hi) & (freqs > 0)).any():
        return
    need = math.ceil(spec.lambda_f_over_d / (dx * (hi - lo)))  # bins no farther apart than the band is wide
    wider = f"optics.focal_n >= {need}, or " if need <= MAX_FOCAL_N else ""
    raise ConfigError(key, list(band), f"holds no frequency of the {m} x {m} optics window: its {m * dx:.3g} m are "
                      f"{m * dx / spec.lambda_f_over_d:.3g} lambda f / W_a (lambda f / W_a = "
                      f"{spec.lambda_f_over_d:.3g} m), so its first frequency above 0 is {freqs[1].item():.3g} of the "
                      f"cutoff W_a / (lambda f); needs {wider}the optics the window was meant for (optics.wavelength_m "
                      f"= {spec.wavelength_m:g}, optics.focal_length_m = {spec.focal_length_m:g}, "
                      f"optics.aperture_diameter_m = {spec.aperture_diameter_m:g})")
