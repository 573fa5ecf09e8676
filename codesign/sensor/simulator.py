"""Physics-based sensor image formation, Sec. 3.2 (Eq. 6-11), differentiable with respect to the PSF.

Irradiances are carried relative to the saturation irradiance I_sat(lambda) of Eq. (ThresSat): r = I / I_sat.
Then the mean photon count per sensor pixel of Eq. (photon_count) is simply mu_p = r e_sat / Q_e (the exposure
time cancels: Eq. 8-9 define the scene and the laser relative to I_sat(t)), and

  background  r_b = alpha_b [b * h + (1 - E_w) mean(b)]  a uniform scene -> alpha_b through any phase mask
              (E_w = energy of h in the optics window; the energy a mask scatters beyond the window arrives as a
              uniform veil of the scene's mean radiance: ``sensor.background_veil``. Without the veil,
              r_b = alpha_b (b * h) / sum(h0), and a uniform scene gives alpha_b BSR(window), 0.87 by default.)
  laser       r_l = alpha_l h(x - f n_l) / h0(0)        uncoded peak -> alpha_l, coded peak -> alpha_l LSR
  electrons   e = Q_e omega + n_c + n_r,  omega ~ N(mu_p, c2^2 mu_p + c1^2 mu_p^2)   (see noise.py)
  counts      s = crop(min(s_sat, round(G min(e_sat, e) + n_q)))

The laser never passes through the scene's FFT: it is placed by exact Fourier interpolation of the window PSF
at its sub-pixel focal offset (kernels.resample_spectrum), evaluated in float64 on its PSF support only, and skipped
when alpha_l = 0 or its support misses the sensor. Saturation: min(e_sat, e) has zero gradient where a pixel is
physically saturated (no signal passes, so none flows back).

Two resolutions (``sensor.path``):
  * full: simulate every sensor pixel (resolution^2, pitch dx), round to integer counts, then downsample to the
    network resolution (area average or antialiased bicubic, ``sensor.downsample``).
  * direct: simulate at the network resolution: the PSF integrated over the coarse pixel (side P = k dx), and
    every noise term given the statistics of the k x k average (std / k, Poisson(k^2 mu_c) / k^2, quantization
    as Gaussian of the averaged rounding variance). Saturation is applied to the average, which is where the two
    differ (measured in docs/sensor.md).
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from typing import Callable

import torch
import torch.nn.functional as F

from codesign.errors import ConfigError
from codesign.optics.propagation import next_fast_len
from codesign.optics.spec import OpticsSpec
from codesign.sensor import kernels
from codesign.sensor.halo import LaserHalo
from codesign.sensor.noise import (
    NoiseStreams,
    dark_current,
    photons,
    read_noise,
    round_ste,
)
from codesign.sensor.spec import SensorSpec, kernel_size


@dataclass
class PSFState:
    """What the simulator needs of the optics: the coded window PSF and the uncoded normalizers.

    psf: (M, M) unit-energy coded PSF on the optics window (pitch dx); uncoded_peak: h0(0) per window sample;
    uncoded_energy: sum of h0 over the window; halo: a callable returning the LaserHalo of the same mask (the
    light beyond the window, computed on first use: only a laser needs it), or None to leave that light out;
    laser: the laser's own PSFState when it shines at another line than the scene (sensor.wavelength_laser_m:
    the mask's surface seen at that wavelength, codesign/optics/lines.py), else None (the laser's PSF is psf).
    """

    psf: torch.Tensor
    uncoded_peak: float
    uncoded_energy: float
    halo: Callable[[], LaserHalo] | None = None
    laser: "PSFState | None" = None
    kernels: dict = field(default_factory=dict, repr=False)  # a laser state's kernels per level (laser_map)


@dataclass
class Level:
    """One simulation grid: pixel pitch, sensor size, kernel size, scene size, FFT size, noise scaling."""

    pitch: float
    n_sensor: int
    ksize: int
    n_scene: int
    n_fft: int
    bins: float  # (pitch / dx)^2: sensor pixels per simulated pixel

    @property
    def noise_scale(self) -> float:
        """sqrt(sum w^2) of the k x k average that maps sensor pixels to this grid's pixels: 1 / k."""
        return self.bins ** -0.5


class SensorSimulator(torch.nn.Module):
    """Scenes + scene parameters + PSF -> sensor counts, network input and ground truths.

    Args:
        sensor: SensorSpec; optics: OpticsSpec (window PSF pitch and size, focal length).
    Geometry (direct path, Table 1 defaults): network pixel P = 2532 / 256 * 5.4 um = 53.4 um; PSF kernel
    ``coarse.ksize`` = 65 pixels (the 640-sample optics window); the scene crop must be
    ``scene_size`` = padded_size + ksize - 1 pixels (448) so that the irradiance target covers the padded grid.
    """

    def __init__(self, sensor: SensorSpec, optics: OpticsSpec, skip_unneeded: bool = True):
        super().__init__()
        self.skip_unneeded = skip_unneeded  # False computes every term even when it is zero (the reference)
        self.sensor, self.optics = sensor, optics
        dx = sensor.pixel_pitch_m
        if abs(optics.focal_pitch_m - dx) > 1e-12 * dx:
            raise ConfigError("sensor.pixel_pitch_m", dx, f"must equal optics.focal_pitch_m ({optics.focal_pitch_m}):"
                              " the optics window is sampled at the sensor pitch")
        if not optics.is_design_wavelength(sensor.wavelength_background_m):
            raise ConfigError("sensor.wavelength_background_m", sensor.wavelength_background_m,
                              f"must equal optics.wavelength_m ({optics.wavelength_m}): the scene is imaged at the "
                              "design wavelength")
        if not any(abs(sensor.wavelength_laser_m - w) <= 1e-12 * w for w in (optics.wavelength_m,
                                                                            *optics.laser_lines)):
            lines = ", ".join(f"{w:g}" for w in optics.laser_wavelengths_m) if optics.laser_wavelengths_m \
                else "null"
            raise ConfigError("sensor.wavelength_laser_m", sensor.wavelength_laser_m,
                              f"must be the design wavelength ({optics.wavelength_m:g}) or one of "
                              f"optics.laser_wavelengths_m ({lines}): the laser's PSF is computed at those lines (add "
                              "the line to optics.laser_wavelengths_m)")
        extent = optics.focal_extent_m
        p = sensor.coarse_pitch_m
        kc = kernel_size(extent, p)
        n_scene = sensor.padded_size + kc - 1
        self.coarse = Level(p, sensor.image_size, kc, n_scene, next_fast_len(n_scene), sensor.bin_factor**2)
        kf = kernel_size(extent, dx)
        nf_scene = sensor.resolution + kf - 1
        self.fine = Level(dx, sensor.resolution, kf, nf_scene, next_fast_len(nf_scene), 1.0)
        # DFT size of the zero-padded window PSF: wide enough for the farthest pixel edge of any level's kernel or
        # laser footprint (ksize / 2 pixels plus half a pixel of sub-pixel offset).
        reach = max((self.footprint_size(lv) / 2 + 1) * lv.pitch for lv in (self.coarse, self.fine))
        self.spectrum_size = kernels.padded_size(optics.focal_n, dx, reach)
        self._cache_key = None
        self._cache = {}

    @staticmethod
    def footprint_size(level: Level) -> int:
        """Laser footprint side in pixels: the kernel plus one pixel each side, so that a footprint centred on
        the nearest pixel still covers the whole window at a half-pixel offset."""
        return level.ksize + 2

    @property
    def scene_size(self) -> int:
        """Side of the (B, 1, S, S) scene crop the simulator expects, at the network resolution."""
        return self.coarse.n_scene

    # ---- PSF kernels, cached per PSF state -----------------------------------------------------------------
    def _kernels(self, state: PSFState, level: Level, key) -> dict:
        ck = (key, level.pitch)
        if key is not None and ck in self._cache:
            return self._cache[ck]
        dx = self.sensor.pixel_pitch_m
        # One float64 spectrum per PSF state serves every level, kernel and laser footprint, so that they are
        # the same interpolant of the window PSF (the laser's peak reaches 1e8 I_sat: float64 keeps it exact).
        psf64 = state.psf.to(torch.float64)
        spectrum = kernels.psf_spectrum(psf64, self.spectrum_size)
        k = kernels.kernel(psf64, dx, level.ksize, level.pitch, self.sensor.pixel_integration,
                           spectrum).to(state.psf.dtype)
        out = {"otf": kernels.kernel_otf(k, level.n_fft), "kernel": k, "spectrum": spectrum, "psf64": psf64}
        if key is not None:
            if key != self._cache_key:
                self._cache = {}
                self._cache_key = key
            self._cache[ck] = out
        return out

    def release_cache(self) -> None:
        """Forget the kept kernels and float64 PSF spectra (tens of MB per PSF state; recomputed, identical, on next
        use): what a pool of many cameras does for the ones not in use."""
        self._cache, self._cache_key = {}, None

    def kernel(self, state: PSFState, level: str = "coarse", key=None) -> torch.Tensor:
        """The pixel-integrated PSF kernel (ksize x ksize energy fractions) the simulator convolves with.

        ``key``: the state's cache key (a frozen mask's ``mask_state_key``): the kernels computed here are then
        kept for the simulations of that state."""
        return self._kernels(state, self.coarse if level == "coarse" else self.fine, key)["kernel"]

    # ---- laser --------------------------------------------------------------------------------------------
    def laser_map(self, state: PSFState, alpha_l: torch.Tensor, angle: torch.Tensor, level: Level, dtype,
                  kd: dict | None = None) -> torch.Tensor | None:
        """r_l on the sensor grid (B, 1, n, n), or None when no sample has a laser on the sensor.

        ``kd``: this level's kernels for this PSF state, if the caller already has them.
        """
        n, ks, pitch = level.n_sensor, self.footprint_size(level), level.pitch
        f = self.optics.focal_length_m
        line = state.laser is not None
        if line:  # the laser at another line: its own PSF, normalizers, halo and kernels
            state, kd = state.laser, state.laser.kernels.get(level.pitch)
        halo = state.halo  # its light reaches the sensor from anywhere (None: sensor.laser_halo is off)
        todo = []  # (sample, first row, first col, laser position in pixels, footprint outside the sensor)
        for i in range(alpha_l.shape[0]):
            if float(alpha_l[i]) == 0.0 and self.skip_unneeded:
                continue
            # angle = (n_u, n_v): u runs along columns (x), v along rows (y), as in the pupil grid.
            pos = (f * angle[i].detach().to(torch.float64).cpu().flip(-1)) / pitch + (n - 1) / 2  # (row, col)
            r0, c0 = (int(v) - ks // 2 for v in torch.round(pos).long())
            outside = r0 >= n or c0 >= n or r0 + ks <= 0 or c0 + ks <= 0
            if outside and self.skip_unneeded and halo is None:
                continue  # footprint entirely outside the sensor
            todo.append((i, r0, c0, pos, outside))
        if not todo:
            return None
        if kd is None:
            kd = self._kernels(state, level, None)
            if line:  # a laser line's kernels are kept on its state: one spectrum per optics evaluation
                state.kernels[level.pitch] = kd
        dev = state.psf.device
        steps = torch.arange(ks, dtype=torch.float64)
        ys = torch.stack([(r0 + steps - pos[0]) * pitch for _, r0, _, pos, _ in todo]).to(dev, non_blocking=True)
        xs = torch.stack([(c0 + steps - pos[1]) * pitch for _, _, c0, pos, _ in todo]).to(dev, non_blocking=True)
        # One product per footprint (a batched product would round differently with the batch's composition and
        # break the bit-identity of the skip paths); each is normalized to the window's energy, then cropped.
        # (Ringing of the truncated window can dip below 0, which is not light: clamped before normalizing.)
        foot = [None if todo[j][4] and self.skip_unneeded else kernels.conserve_energy(kernels.resample_spectrum(
            kd["spectrum"], self.sensor.pixel_pitch_m, ys[j], xs[j], pitch, self.sensor.pixel_integration
        ).clamp_min(0), kd["psf64"]) for j in range(len(todo))]
        out = torch.zeros(alpha_l.shape[0], 1, n, n, dtype=dtype, device=dev)
        norm = state.uncoded_peak * level.bins
        if halo is not None:  # the light beyond the window: (1 - window energy) x the halo's shape, per pixel
            far, beyond = halo(), (1.0 - state.psf.detach().to(torch.float64).sum()).clamp_min(0)
            for i, _, _, pos, _ in todo:
                spot = ((pos - (n - 1) / 2) * pitch).tolist()
                block = alpha_l[i].to(device=dev, dtype=torch.float64, non_blocking=True) * beyond \
                    * far.pixel_energy(spot, n, pitch).to(dev) / norm
                out[i, 0] += block.to(dtype)
        for j, (i, r0, c0, _, outside) in enumerate(todo):
            if outside:  # nothing of the footprint lands on the sensor (the halo may: added above)
                continue
            r_lo, r_hi, c_lo, c_hi = max(r0, 0), min(r0 + ks, n), max(c0, 0), min(c0 + ks, n)
            patch = foot[j][r_lo - r0: r_hi - r0, c_lo - c0: c_hi - c0]
            block = (alpha_l[i].to(device=dev, dtype=torch.float64, non_blocking=True) * patch / norm).to(dtype)
            at = torch.full((), i, dtype=torch.long, device=dev)  # made on the device: no host copy to wait for
            out = out.index_put((at, torch.zeros_like(at), torch.arange(r_lo, r_hi, device=dev)[:, None],
                                 torch.arange(c_lo, c_hi, device=dev)[None, :]), block, accumulate=True)
        return out

    # ---- the pipeline -------------------------------------------------------------------------------------
    def forward(self, scene: torch.Tensor, params, state: PSFState, seed: int, mask_key=None) -> dict:
        """Simulate a batch.

        Args:
            scene: (B, 1, S, S) radiance in [0, 1] at the network resolution, S = ``scene_size``.
            params: SceneParams (batched alpha_l, alpha_b, laser_angle_rad, c1, c2, noise and exposure values).
            state: PSFState of the current mask; seed: base seed of the noise streams.
            mask_key: hashable identity of a frozen mask state; kernels are cached under it (None: recompute).
        Returns dict of tensors:
            sensor_dn (B,1,n,n) digital counts; sensor (B,1,pad,pad) normalized input DN / (G e_sat), zero padded;
            irradiance (B,1,pad,pad) target r_b = I_b / I_sat (uncropped); scene (B,1,pad,pad) target b;
            saturated (B,1,n,n) bool; laser (B,1,n,n) r_l at the network resolution (zeros if none).
        """
        s, sp = self.sensor, params
        if scene.dim() != 4 or scene.shape[1] != 1 or scene.shape[-1] != self.scene_size \
                or scene.shape[-2] != self.scene_size:
            raise ValueError(f"scene must have shape (B, 1, {self.scene_size}, {self.scene_size}), got "
                             f"{tuple(scene.shape)}")
        dtype, dev = scene.dtype, scene.device
        # params may stay on the host (the training data keeps them there): every decision below reads them
        # there, and values reach the device without waiting for it (no host-device sync in a training step)
        col = lambda v: v.to(dtype=dtype, device=dev, non_blocking=True).reshape(-1, 1, 1, 1)  # noqa: E731
        c = self.coarse
        kc = self._kernels(state, c, mask_key)
        scene_mean = scene.mean(dim=(-2, -1), keepdim=True)
        irr = col(sp.alpha_b) * self._background(scene, kc, c, state, scene_mean)
        pad, n = s.padded_size, s.image_size
        m = (pad - n) // 2
        target_scene = scene[..., c.ksize // 2: c.ksize // 2 + pad, c.ksize // 2: c.ksize // 2 + pad]
        streams = NoiseStreams(seed, dev)
        if s.path == "direct":
            r_b = irr[..., m:m + n, m:m + n]
            lvl, kl = c, kc
        else:
            lvl = self.fine
            kl = self._kernels(state, lvl, mask_key)
            r_b = col(sp.alpha_b) * self._fine_background(scene, state, kl, scene_mean)
        laser = self.laser_map(state, sp.alpha_l, sp.laser_angle_rad, lvl, dtype, kl)
        r = r_b if laser is None else r_b + laser
        dn, sat = self._digitize(r, sp, col, lvl.noise_scale, streams, exact_rounding=(s.path == "full"))
        if s.path == "full":
            dn, sat, laser = self._downsample(dn, sat, laser)
        out = {
            "sensor_dn": dn,
            "sensor": F.pad(dn / (s.gain_dn_per_e * s.full_well_e), (m, pad - n - m, m, pad - n - m)),
            "irradiance": irr, "scene": target_scene, "saturated": sat,
            "laser": laser if laser is not None else torch.zeros_like(dn),
        }
        return out

    def _digitize(self, r, sp, col, scale: float, streams, exact_rounding: bool):
        """Photons -> electrons -> counts; ``scale`` = the level's noise_scale (1 / k for a k x k average)."""
        s = self.sensor
        w2 = scale**2
        mu_p = r * (s.full_well_e / s.quantum_efficiency)
        # which terms to skip is decided on ``sp`` where it lives (the host for training batches), the terms
        # themselves run unconditionally (skip=False) on the device
        needed = lambda *v: not self.skip_unneeded or any(bool((t != 0).any()) for t in v)  # noqa: E731
        omega = photons(mu_p, col(sp.c1), col(sp.c2), scale, streams, False) if needed(sp.c1, sp.c2) else mu_p
        e = s.quantum_efficiency * omega
        if needed(sp.dark_current_mean_e):
            e = e + dark_current(col(sp.dark_current_mean_e), e, 1.0 / w2, streams, False)
        if needed(sp.read_noise_std_e):
            e = e + read_noise(col(sp.read_noise_mean_e), col(sp.read_noise_std_e), e, scale, streams, False)
        else:
            e = e + col(sp.read_noise_mean_e)
        sat = e >= s.full_well_e
        e = e.clamp(0.0, s.full_well_e)  # full well; zero gradient where saturated
        dn = s.gain_dn_per_e * e
        if exact_rounding:  # dither U(-0.5, 0.5), then round to integer counts (straight-through gradient)
            # in float64: float32 spaces counts near full well 1e-3 apart, so G e_sat + u rounded up to 9435.5 and
            # then to 9436 for u > 0.4995, a count above full well (in 7e-4 of the saturated float32 pixels)
            dn64 = dn.to(torch.float64)
            dn = round_ste(dn64 + streams.uniform("quant", dn64)).to(dn.dtype)
        else:  # the k x k average of (dither + rounding), each uniform with variance 1/12; a saturated pixel
            # reads G e_sat exactly in every sensor pixel, so it gets none
            dn = dn + math.sqrt(w2 / 6.0) * streams.normal("quant", dn) * (~sat).to(dn.dtype)
        return dn.clamp(0.0, s.saturation_dn), sat

    def _background(self, scene: torch.Tensor, kd: dict, level: Level, state: PSFState,
                    scene_mean: torch.Tensor) -> torch.Tensor:
        """(b * h) plus the out-of-window veil, normalized so that a uniform scene gives 1 (see module doc).

        ``scene_mean``: (B, 1, 1, 1) mean radiance of the whole scene crop at the network resolution (the widest
        view the simulator has), shared by both paths so that they add the same veil.
        """
        conv = kernels.convolve_valid(scene, kd["otf"].to(scene.device), level.n_fft, level.ksize)
        if not self.sensor.background_veil:
            return conv / state.uncoded_energy
        outside = 1.0 - state.psf.sum()  # energy the mask scatters beyond the window (differentiable)
        return conv + outside.to(conv.dtype) * scene_mean

    def _fine_background(self, scene, state, kd, scene_mean):
        """r_b / alpha_b at sensor resolution: the scene resampled (bicubic) onto the sensor-pixel grid, then
        convolved."""
        dtype = scene.dtype
        f, c = self.fine, self.coarse
        fine_c = kernels.symmetric_coords(f.n_scene, f.pitch, scene.device) / c.pitch + (c.n_scene - 1) / 2
        g = (fine_c * 2 / (c.n_scene - 1) - 1).to(dtype)  # align_corners=True normalization
        gy, gx = torch.meshgrid(g, g, indexing="ij")
        grid = torch.stack([gx, gy], -1)[None].expand(scene.shape[0], -1, -1, -1)
        # border: the outermost sensor-pixel centres lie up to half a network pixel beyond the outermost scene
        # centres; zeros there would darken the border, the nearest scene value is the better guess.
        fine_scene = F.grid_sample(scene, grid, mode="bicubic", padding_mode="border",
                                   align_corners=True).clamp(0, 1)
        return self._background(fine_scene, kd, f, state, scene_mean)

    def _downsample(self, dn, sat, laser):
        n = self.sensor.image_size
        if self.sensor.downsample == "area":
            down = lambda x: F.adaptive_avg_pool2d(x, n)  # noqa: E731
        else:
            down = lambda x: F.interpolate(x, size=(n, n), mode="bicubic", antialias=True,  # noqa: E731
                                           align_corners=False)
        # bicubic rings (negative lobes) at the edges of a saturated footprint: clamp back to what can be read
        laser_d = None if laser is None else down(laser).clamp_min(0)
        lo, hi = dn.amin(dim=(-2, -1), keepdim=True), dn.amax(dim=(-2, -1), keepdim=True)
        dn_d = torch.minimum(torch.maximum(down(dn), lo), hi)  # no overshoot beyond what the sensor read
        return dn_d, down(sat.to(dn.dtype)) >= 0.5, laser_d


def psf_state(system, phase: torch.Tensor, cell_m: float | None = None) -> PSFState:
    """PSFState of an OpticalSystem for a pupil phase (differentiable through ``psf``)."""
    return PSFState(psf=system.psf(phase, cell_m), uncoded_peak=system.uncoded_peak,
                    uncoded_energy=system.uncoded_energy)


def mask_state_key(mask) -> tuple | None:
    """Key of a frozen mask's parameter values (None while any parameter is being trained).

    A digest of the values themselves: version counters miss writes through ``.data``.
    """
    params = list(mask.parameters())
    if torch.is_grad_enabled() and any(p.requires_grad for p in params):
        return None
    digest = hashlib.blake2b(digest_size=16)
    for p in params:
        digest.update(p.detach().cpu().contiguous().numpy().tobytes())
    return (id(mask), digest.hexdigest())
