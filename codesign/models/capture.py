"""Restoring a real capture: any size and aspect, from a sensor of the configured pitch, at the pixel scale asked for.

A camera gives sensor counts (DN) at its own pitch dx (the paper's 2532 x 2532 at 5.4 um, a 1920 x 1080 frame); a
restorer works at a network pixel of ``bin`` sensor pixels (the paper downsampled 2532 px to 256: bin 9.89). So:

1. bin: the counts averaged over network pixels of bin x bin sensor pixels (exact area weights, any real bin >= 1;
   ``bin_counts``); a network pixel holding a saturated sensor pixel is marked saturated (its value is no longer a
   measurement of the scene), then normalized to the full well as the simulator normalizes its network input;
2. the kernel: the camera's window PSF (the run's mask and optics, or a measured PSF) integrated over the network
   pixel, on a canvas that pads the image by the kernel's reach (zeros, as in training: the deconvolution does not
   wrap), and its OTF on that canvas;
3. the restorer, whole or (``tile``) with its local decoder in overlapping tiles after one global deconvolution
   (a model with ``restore_tiled``), the result cropped back to the image.

Everything here is shape-generic: no square or fixed-size assumption. The networks that take any size are those
with ``any_size`` (WienerNAF); the others need the canvas they were trained on.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Mapping

import torch
import torch.nn.functional as F

from codesign.config.store import register, spec_node
from codesign.errors import ConfigError, require_number
from codesign.models.fill import SATURATED
from codesign.spec_base import SpecMixin
from codesign.sensor import kernels
from codesign.sensor.spec import kernel_size


AUTO_TILE_PX = 1536**2  # a canvas above this many pixels is decoded in tiles (restore.tile: null)
AUTO_TILE = 512


@dataclass(frozen=True)
class RestoreSpec(SpecMixin):
    """bin: sensor pixels per network pixel, a real number >= 1 (1: full resolution; null: the finest pixel scale
    the network was trained at, e.g. 2532 / 256 = 9.89 for data.scales up to 256, or its data.image_size's);
    input_bin: sensor pixels per capture pixel (1: a raw capture; a capture already binned, e.g. one
    +experiment=simulate wrote at data.image_size: sensor.resolution / data.image_size), at most bin;
    tile: the side of the tiles the decoder runs on (null: whole up to a canvas of 1536^2 pixels, else 512)."""

    bin: float | None = None
    input_bin: float = 1.0
    tile: int | None = None
    prefix: str = field(default="restore", compare=False, repr=False)

    def __post_init__(self) -> None:
        p = self.prefix
        if self.bin is not None:
            object.__setattr__(self, "bin", float(require_number(f"{p}.bin", self.bin, lo=1, hi=1e4)))
        object.__setattr__(self, "input_bin", float(require_number(f"{p}.input_bin", self.input_bin, lo=1, hi=1e4)))
        if self.tile is not None:
            object.__setattr__(self, "tile", require_number(f"{p}.tile", self.tile, lo=32, hi=65536, integer=True))

    def tile_for(self, geometry: "CaptureGeometry") -> int | None:
        """The tile side to decode ``geometry``'s canvas with (None: whole)."""
        if self.tile is not None:
            return self.tile
        rows, cols = geometry.canvas
        return AUTO_TILE if rows * cols > AUTO_TILE_PX else None


def network_bin(config: Mapping) -> float:
    """Sensor pixels per network pixel a checkpoint works at, from its configuration: its finest trained pixel scale
    (data.scales), else its data.image_size (the whole sensor binned to it)."""
    scales = config["data"].get("scales")
    return int(config["sensor"]["resolution"]) / (max(scales) if scales else int(config["data"]["image_size"]))


def capture_factor(spec: RestoreSpec, config: Mapping) -> float:
    """Capture pixels per network pixel: (restore.bin or the checkpoint's network_bin) / restore.input_bin;
    ConfigError when that asks for a network pixel finer than the capture's."""
    factor = (spec.bin if spec.bin is not None else network_bin(config)) / spec.input_bin
    if factor < 1 - 1e-9:
        raise ConfigError(f"{spec.prefix}.input_bin", spec.input_bin, f"is coarser than the network pixel ("
                          f"{spec.bin if spec.bin is not None else network_bin(config):.4g} sensor pixels): a capture "
                          "is binned to the network's scale, never upsampled")
    return max(factor, 1.0)


def _area_weights(n_in: int, n_out: int, factor: float, dtype) -> torch.Tensor:
    """(n_out, n_in): the share of each input pixel [i, i + 1) in each output pixel [j f, (j + 1) f), over f."""
    edges_out = torch.arange(n_out + 1, dtype=torch.float64) * factor
    lo = torch.maximum(edges_out[:-1, None], torch.arange(n_in, dtype=torch.float64)[None, :])
    hi = torch.minimum(edges_out[1:, None], torch.arange(1, n_in + 1, dtype=torch.float64)[None, :])
    return ((hi - lo).clamp_min(0) / factor).to(dtype)


def binned_shape(shape: tuple[int, int], factor: float) -> tuple[int, int]:
    """(rows, columns) of a capture of ``shape`` binned by ``factor``: every whole network pixel it holds."""
    return tuple(max(1, math.floor(n / factor + 1e-9)) for n in shape)


def bin_counts(counts: torch.Tensor, factor: float, full_scale: float) -> torch.Tensor:
    """(..., H, W) counts -> (..., h, w) area averages over ``factor`` x ``factor`` pixels (h = floor(H / factor),
    the partial last row and column dropped); a network pixel touching a saturated count (>= SATURATED x
    ``full_scale``) reads ``full_scale`` (clipped: no longer a measurement of the scene). factor 1: unchanged."""
    if factor == 1:
        return counts
    h, w = binned_shape(tuple(counts.shape[-2:]), factor)
    x = counts.to(torch.float64)
    rows = _area_weights(counts.shape[-2], h, factor, x.dtype).to(x.device)
    cols = _area_weights(counts.shape[-1], w, factor, x.dtype).to(x.device)
    out = rows @ x @ cols.T
    clipped = (rows @ (x >= SATURATED * full_scale).to(x.dtype) @ cols.T) > 0
    return torch.where(clipped, torch.full_like(out, full_scale), out).to(counts.dtype)


@dataclass(frozen=True)
class CaptureGeometry:
    """Where a binned capture sits for the restorer. factor: sensor pixels per network pixel; pitch_m: the network
    pixel [m]; size: (h, w) of the binned image; kernel: the PSF kernel's side [network px]; canvas: (rows,
    columns) of the padded grid; offset: (top, left) of the image on it."""

    factor: float
    pitch_m: float
    size: tuple[int, int]
    kernel: int
    canvas: tuple[int, int]
    offset: tuple[int, int]


def capture_geometry(shape: tuple[int, int], factor: float, pixel_pitch_m: float, focal_extent_m: float,
                     multiple: int = 8) -> CaptureGeometry:
    """The geometry of a (H, W) capture binned by ``factor``: the image padded by the PSF kernel's reach on every
    side (canvas >= image + kernel - 1, each side a multiple of ``multiple``), centred."""
    size = binned_shape(shape, factor)
    pitch = pixel_pitch_m * factor
    k = kernel_size(focal_extent_m, pitch)
    canvas = tuple(-(-(n + k - 1) // multiple) * multiple for n in size)
    offset = tuple((c - n) // 2 for c, n in zip(canvas, size))
    return CaptureGeometry(factor, pitch, size, k, canvas, offset)


def capture_otf(psf: torch.Tensor, dx: float, geometry: CaptureGeometry, integrate: bool = True) -> torch.Tensor:
    """OTF on the capture's canvas of the window PSF (M x M samples at the sensor pitch ``dx`` [m]) integrated over
    the network pixel (``integrate``, as the sensor does) or point-sampled."""
    k = kernels.kernel(psf.detach().to(torch.float64), dx, geometry.kernel, geometry.pitch_m, integrate)
    return kernels.otf_from_kernel(k.to(torch.float32), geometry.canvas)


def normalized_canvas(counts: torch.Tensor, geometry: CaptureGeometry, full_well_dn: float) -> torch.Tensor:
    """(C, h, w) binned counts -> (1, C, rows, columns): divided by the full well in DN (the network input's
    scale: 1 at saturation), zero-padded onto the canvas."""
    top, left = geometry.offset
    (h, w), (rows, cols) = geometry.size, geometry.canvas
    x = (counts.to(torch.float32) / full_well_dn).clamp(0, 1)
    return F.pad(x, (left, cols - w - left, top, rows - h - top))[None]


def restore_capture(model, counts: torch.Tensor, psf: torch.Tensor, sensor, geometry: CaptureGeometry,
                    generators=None, tile: int | None = None,
                    progress: Callable[[int, int], None] | None = None) -> torch.Tensor:
    """Restore one capture: (C, H, W) or (H, W) counts [DN] from a sensor ``sensor`` (SensorSpec: pitch, gain, full
    well, pixel integration) whose window PSF is ``psf`` (samples at the sensor pitch), binned and placed as
    ``geometry`` says (capture_geometry). Returns (C, h, w) at the sensor's exposure, normalized to the full well.
    ``tile``: decode in tiles of this side (models with restore_tiled), None = whole."""
    if not model.any_size:
        raise ConfigError("checkpoint", model.kind, "restores captures of its training size only; a capture of any "
                          "size needs a network that takes any size (model=wiener_naf, e.g. checkpoint=pretrained)")
    x = counts if counts.dim() == 3 else counts[None]
    full_well_dn = sensor.gain_dn_per_e * sensor.full_well_e
    binned = bin_counts(x.to(torch.float64), geometry.factor, min(full_well_dn, sensor.saturation_dn))
    canvas = normalized_canvas(binned, geometry, full_well_dn).to(psf.device)
    otf = capture_otf(psf, sensor.pixel_pitch_m, geometry, sensor.pixel_integration).to(psf.device)
    with torch.no_grad():
        if tile is None:
            out = model.restore(canvas, otf, generators)["restored"]
        else:
            out = model.restore_tiled(canvas, otf, tile, generators, progress)
    top, left = geometry.offset
    h, w = geometry.size
    return out[0, :, top:top + h, left:left + w]

register("restore", "default", spec_node(RestoreSpec))
