"""Restorability: how well a scene can be restored through this optics, in closed form and differentiable.

Model, at the network resolution (n x n field, pitch P, where restorers work): the normalized sensor image is
y = a (h * b) + noise, with a = alpha_b (the background strength), h the PSF kernel integrated over a network pixel
(the camera's kernel; H its DFT on the field), b the scene and white noise of variance sigma^2 per pixel. The
linear MMSE (Wiener) estimate of b has, per DFT frequency f (orthonormal DFT), the expected error

    e(f) = S(f) N / (|H(f)|^2 S(f) + N),    N = sigma^2 / a^2  (the noise in scene units),

and the expected per-pixel MSE is mean_f e(f) over f != 0 (the mean brightness is not restoration: evaluation
compares after a gain / offset match). S is a natural-scene power spectrum, S(f) = A |f|^-beta, fitted to the
built-in training scenes (or given). sigma^2 is the sensor model's noise at a mean signal level (codesign/sensor):
    sigma^2 = w2 [c2^2 Q_e r / e_sat + c1^2 r^2 + (mu_c + sigma_r^2) / e_sat^2 + 1 / (6 G^2 e_sat^2)],
r = alpha_b b: the photon term at the scene's mean, the photo-response term c1^2 r^2 at its mean square,
w2 = 1 / k^2 for the k x k sensor pixels a network pixel averages.

Two shares of the field carry no usable information and cost scene variance (v per pixel) instead of the Wiener
error:
  * the field's edge: a pixel within the PSF's reach of the field's border receives light from scene the camera
    never sees whole. A deconvolution of the field can only take that light for the field's own, so its error
    there is the difference of two unrelated scene values, of variance 2v (``edge_cost`` = 2). The share is
    L_edge = sum_u h(u) [1 - (1 - |u_y| / n)(1 - |u_x| / n)]: the mean over the field's pixels of the light each
    receives from beyond the border. Without this term the figure ranks wide PSFs (the published mask's) far
    above what Wiener filters measure on simulated captures (benchmarks: design, restorability validation,
    which also reports the ranking with edge_cost 1 and without the term).
  * optionally the field lost to saturation at laser strength alpha_l: the pixels where the laser's footprint
    alpha_l h / h0(0) plus the background reach full well, each costing v; their share L_sat is a soft (sigmoid)
    count, so it stays differentiable.
MSE = (1 - L_edge - L_sat) mean_f e(f) + (edge_cost L_edge + L_sat) v. Reported as an expected PSNR (peak 1) in
dB; higher is better.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from codesign.data.params import FIGURE_VALUES


@dataclass(frozen=True)
class SceneSpectrum:
    """S(f) = amplitude |f|^-exponent, f in cycles per pixel, per orthonormal-DFT coefficient of a [0, 1] scene."""

    amplitude: float
    exponent: float

    def __call__(self, f: torch.Tensor) -> torch.Tensor:
        return self.amplitude * f.clamp_min(1e-12) ** (-self.exponent)


def fit_scene_spectrum(scenes: torch.Tensor) -> SceneSpectrum:
    """Least-squares fit of log S = log A - beta log f to the radial mean power of (N, 1, n, n) scenes in [0, 1]
    (each scene's mean removed, a separable Hann window against the edge discontinuity; ortho DFT),
    over 2 / n <= f <= 0.4 cycles per pixel."""
    x = scenes.to(torch.float64)
    n = x.shape[-1]
    x = x - x.mean(dim=(-2, -1), keepdim=True)
    win = torch.hann_window(n, periodic=False, dtype=torch.float64)
    w2 = (win[:, None] * win[None, :])
    x = x * w2 / w2.pow(2).mean().sqrt()  # windowed, power preserved on average
    power = (torch.fft.fft2(x, norm="ortho").abs() ** 2).mean(dim=(0, 1))
    f = torch.fft.fftfreq(n, dtype=torch.float64)
    fr = torch.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    sel = (fr >= 2.0 / n) & (fr <= 0.4)
    lf, lp = torch.log(fr[sel]), torch.log(power[sel])
    design = torch.stack([torch.ones_like(lf), lf], 1)
    coef = torch.linalg.lstsq(design, lp[:, None]).solution[:, 0]
    return SceneSpectrum(float(torch.exp(coef[0])), float(-coef[1]))


def noise_variance(sensor, params: dict | None = None, mean_scene: float = 0.5,
                   mean_square: float | None = None) -> float:
    """sigma^2 of the normalized sensor image per network pixel, averaged over the scene's pixels (see the module
    docstring); ``params``: scene parameters (default: the paper's figure values); ``mean_square``: the scene's
    mean of b^2 (default mean_scene^2, a uniform scene)."""
    p = {**FIGURE_VALUES, **(params or {})}
    w2 = 1.0 / sensor.bin_factor**2
    a = p["alpha_b"]
    r, r2 = a * mean_scene, a**2 * (mean_scene**2 if mean_square is None else mean_square)
    e_sat = sensor.full_well_e
    return w2 * (p["c2"] ** 2 * sensor.quantum_efficiency * r / e_sat + p["c1"] ** 2 * r2
                 + (p["dark_current_mean_e"] + p["read_noise_std_e"] ** 2) / e_sat**2
                 + 1.0 / (6.0 * sensor.gain_dn_per_e**2 * e_sat**2))


class Restorability(torch.nn.Module):
    """Expected Wiener PSNR [dB] of a network-pitch PSF kernel on an n x n field (see the module docstring).

    Args:
        n: field side in network pixels (data.image_size); spectrum: the scene power spectrum; noise: sigma^2;
        alpha_b: background strength a; scene_variance: per-pixel variance of the scene (for lost pixels);
        alpha_l: laser strength whose saturated footprint is counted (None: no laser); uncoded_peak: h0(0) per
        optics-window sample; bins: optics-window samples per network pixel ((P / dx)^2); softness: width of the
        saturation's sigmoid, relative to full well; edge: count the light from beyond the field's border as lost
        (False: the circular model, an infinite field); edge_cost: what that light costs, in scene variances.
    """

    def __init__(self, n: int, spectrum: SceneSpectrum, noise: float, alpha_b: float = FIGURE_VALUES["alpha_b"],
                 scene_variance: float = 0.06, alpha_l: float | None = None, uncoded_peak: float = 1.0,
                 bins: float = 1.0, softness: float = 0.05, edge: bool = True, edge_cost: float = 2.0):
        super().__init__()
        self.n, self.spectrum, self.noise, self.alpha_b = n, spectrum, float(noise), float(alpha_b)
        self.edge, self.edge_cost = edge, float(edge_cost)
        self.scene_variance, self.alpha_l = float(scene_variance), alpha_l
        self.uncoded_peak, self.bins, self.softness = float(uncoded_peak), float(bins), float(softness)
        f = torch.fft.fftfreq(n, dtype=torch.float64)
        fr = torch.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
        s = spectrum(fr)
        s[0, 0] = 0.0  # the mean is not restoration
        self.register_buffer("s", s, persistent=False)

    def otf(self, kernel: torch.Tensor) -> torch.Tensor:
        """|H|^2 (n, n) of a centred odd (k, k) kernel (energy fractions) on the n x n field."""
        k = kernel.shape[-1]
        c = k // 2
        pad = kernel.new_zeros(self.n, self.n).to(torch.float64)
        size = min(k, self.n)
        lo = c - size // 2
        pad[:size, :size] = kernel.to(torch.float64)[lo:lo + size, lo:lo + size]
        h = torch.fft.fft2(torch.roll(pad, (-(size // 2), -(size // 2)), (0, 1)))
        return h.real**2 + h.imag**2

    def mse(self, kernel: torch.Tensor) -> torch.Tensor:
        """Expected per-pixel MSE of the Wiener estimate (float64, differentiable in ``kernel``)."""
        h2 = self.otf(kernel)
        n_scene = self.noise / self.alpha_b**2
        err = self.s * n_scene / (h2 * self.s + n_scene)
        mse = err.sum() / self.n**2
        if self.edge:
            lost = self.edge_fraction(kernel)
            mse = (1 - lost) * mse + self.edge_cost * lost * self.scene_variance
        if self.alpha_l:
            lost = self.lost_fraction(kernel)
            mse = mse - lost * err.sum() / self.n**2 + lost * self.scene_variance
        return mse

    def edge_fraction(self, kernel: torch.Tensor) -> torch.Tensor:
        """L_edge: the mean over the n x n field's pixels of the light each receives from beyond the field,
        sum_u h(u) [1 - (1 - |u_y| / n)+ (1 - |u_x| / n)+] for a centred odd (k, k) kernel h."""
        k = kernel.shape[-1]
        u = (torch.arange(k, dtype=torch.float64, device=kernel.device) - k // 2).abs()
        inside = (1 - u / self.n).clamp_min(0)
        return (kernel.to(torch.float64) * (1 - inside[:, None] * inside[None, :])).sum()

    def lost_fraction(self, kernel: torch.Tensor) -> torch.Tensor:
        """The soft share of the field saturated by the laser on axis (0 without a laser)."""
        laser = self.alpha_l * kernel.to(torch.float64) / (self.uncoded_peak * self.bins)
        level = laser + self.alpha_b * 0.5  # the background at the mean scene
        return torch.sigmoid((level - 1.0) / self.softness).sum() / self.n**2

    def forward(self, kernel: torch.Tensor) -> torch.Tensor:
        """Expected PSNR [dB] = 10 log10(1 / MSE)."""
        return -10.0 * torch.log10(self.mse(kernel))


def restorability_for(camera, scenes: torch.Tensor | None = None, spectrum: SceneSpectrum | None = None,
                      alpha_l: float | None = None, params: dict | None = None) -> Restorability:
    """The Restorability of a Camera's geometry and sensor, with the spectrum fitted to ``scenes`` (N, 1, n, n)
    when it is not given."""
    sensor = camera.sensor
    if spectrum is None:
        spectrum = fit_scene_spectrum(scenes)
    x = scenes.to(torch.float64) if scenes is not None else None
    var = float(x.var(dim=(-2, -1)).mean()) if x is not None else 0.06
    mean, square = (float(x.mean()), float(x.square().mean())) if x is not None else (0.5, None)
    p = {**FIGURE_VALUES, **(params or {})}
    bins = (camera.simulator.coarse.pitch / camera.optics.focal_pitch_m) ** 2
    return Restorability(sensor.image_size, spectrum, noise_variance(sensor, p, mean, square), p["alpha_b"], var,
                         alpha_l, camera.system.uncoded_peak, bins)


def psnr_of_mse(mse: float) -> float:
    """PSNR [dB] of a mean squared error on images in [0, 1]."""
    return -10.0 * math.log10(mse)
