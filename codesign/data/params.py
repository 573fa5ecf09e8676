"""Per-scene simulation parameters (laser, background, sensor noise, exposure) and their sampling (Sec. 6.2).

Every parameter is a batched tensor so that one simulated batch can mix laser strengths, incidence angles and
noise levels, as the paper's online training does. Units: radians, electrons (e-), seconds; strengths are
dimensionless (alpha_l = uncoded laser peak irradiance / sensor saturation irradiance I_sat, Eq. 5).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Sequence

import torch

from codesign.data.paramconfig import ParamConfig
from codesign.errors import ConfigError, require_number

__all__ = ["SceneParams", "sample_scene_params", "fixed_scene_params", "preset_params", "preset_names",
           "LASER_STRENGTHS", "FIGURE_VALUES", "ROBUSTNESS_FIXED", "ROBUSTNESS_STAGES", "PRESETS",
           "laser_strength_levels"]


def laser_strength_levels(pc: ParamConfig) -> torch.Tensor:
    """The predetermined laser strengths the training draws from, float64, ascending (see sample_scene_params).
    Both ends of ``alpha_l_range`` are levels (ParamConfig.from_config refuses a single level for a range of two values)."""
    (lo, hi), n = pc.alpha_l_range, pc.alpha_l_levels
    if pc.alpha_l_spacing == "linear" or lo == hi:
        return torch.linspace(lo, hi, n, dtype=torch.float64)
    if pc.alpha_l_spacing == "mixed":  # half the levels of each grid: a uniform draw is a 50/50 mixture of the two
        half = [dataclasses.replace(pc, alpha_l_spacing=s, alpha_l_levels=k)
                for s, k in (("linear", n - n // 2), ("log", n // 2))]
        return torch.sort(torch.cat([laser_strength_levels(h) for h in half])).values
    return _log_levels(lo, hi, n)


def _log_levels(lo: float, hi: float, n: int) -> torch.Tensor:
    zero = lo == 0
    # geometric from lo (from 1 when lo = 0, with 0 as one more level); one geometric level is the upper end
    # (torch.logspace of one step gives its start: with lo = 0 and 2 levels the grid was {0, 1}, not {0, hi})
    count, start = n - zero, lo if lo > 0 else 1.0
    levels = torch.logspace(math.log10(start), math.log10(hi), count, dtype=torch.float64) \
        if count > 1 else torch.tensor([hi], dtype=torch.float64)
    levels[0], levels[-1] = (start if count > 1 else hi), hi  # the ends exactly (10 ** log10(hi) may miss hi)
    return torch.cat([torch.zeros(1, dtype=torch.float64), levels]) if zero else levels


# Field names of SceneParams with shape (B,); laser_angle_rad is the one (B, 2) field.
SCALAR_FIELDS = ("alpha_l", "alpha_b", "c1", "c2", "dark_current_mean_e", "read_noise_mean_e",
                 "read_noise_std_e", "exposure_s")
FIELDS = ("alpha_l", "alpha_b", "laser_angle_rad", "c1", "c2", "dark_current_mean_e", "read_noise_mean_e",
          "read_noise_std_e", "exposure_s")


@dataclass(frozen=True)
class SceneParams:
    """Scene and sensor parameters of a batch of B simulated captures. All float tensors on one device.

    alpha_l:             (B,)   laser strength: uncoded laser peak irradiance / I_sat (0 = no laser)
    alpha_b:             (B,)   background strength: scene peak irradiance scale (Eq. 6), dimensionless
    laser_angle_rad:     (B, 2) laser incidence (n_u, n_v) in radians; small angle: focal-plane offset = f * angle
    c1:                  (B,)   relative std of the signal-proportional photon noise (0.2 = 20 %)
    c2:                  (B,)   photon-noise std modulation (dimensionless)
    dark_current_mean_e: (B,)   dark current mean mu_c, electrons
    read_noise_mean_e:   (B,)   read noise mean mu_r, electrons
    read_noise_std_e:    (B,)   read noise std sigma_r, electrons
    exposure_s:          (B,)   exposure time t, seconds
    """

    alpha_l: torch.Tensor
    alpha_b: torch.Tensor
    laser_angle_rad: torch.Tensor
    c1: torch.Tensor
    c2: torch.Tensor
    dark_current_mean_e: torch.Tensor
    read_noise_mean_e: torch.Tensor
    read_noise_std_e: torch.Tensor
    exposure_s: torch.Tensor

    def __post_init__(self):
        b = self.alpha_l.shape[0] if self.alpha_l.dim() == 1 else -1
        for name in SCALAR_FIELDS:
            t = getattr(self, name)
            if not isinstance(t, torch.Tensor) or t.shape != (b,) or b < 1:
                raise ValueError(f"SceneParams.{name} must be a tensor of shape (B,) = ({b},), "
                                 f"got {tuple(getattr(t, 'shape', ()))}")
        if not isinstance(self.laser_angle_rad, torch.Tensor) or self.laser_angle_rad.shape != (b, 2):
            raise ValueError(f"SceneParams.laser_angle_rad must have shape (B, 2) = ({b}, 2), "
                             f"got {tuple(getattr(self.laser_angle_rad, 'shape', ()))}")

    @property
    def batch_size(self) -> int:
        """The number of scenes the parameters describe (B)."""
        return int(self.alpha_l.shape[0])

    def __len__(self) -> int:
        return self.batch_size

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "SceneParams":
        """Copy onto ``device`` / cast to floating ``dtype`` (either may be None = unchanged)."""
        return SceneParams(**{k: getattr(self, k).to(device=device, dtype=dtype) for k in FIELDS})

    def index(self, i: int) -> "SceneParams":
        """Sample ``i`` (negative counts from the end) as a SceneParams of batch 1."""
        b = self.batch_size
        if not -b <= i < b:
            raise IndexError(f"SceneParams.index({i}) out of range for batch size {b}")
        i = i % b
        return SceneParams(**{k: getattr(self, k)[i:i + 1] for k in FIELDS})

    def part(self, part: slice) -> "SceneParams":
        """The samples ``part`` of the batch (a distributed rank's share of a global batch)."""
        out = {k: getattr(self, k)[part] for k in FIELDS}
        if out["alpha_l"].shape[0] < 1:
            raise IndexError(f"SceneParams.part({part}) is empty for batch size {self.batch_size}")
        return SceneParams(**out)

    def replace(self, **values: Any) -> "SceneParams":
        """A copy with some fields set to constants (or full tensors); e.g. ``p.replace(alpha_l=1e6)``.

        The paper's laser-strength sweep keeps the other sampled parameters and varies alpha_l only, so this
        is how an evaluation builds one batch per strength from one sampled batch.
        """
        unknown = sorted(set(values) - set(FIELDS))
        if unknown:
            raise ConfigError(unknown[0], values[unknown[0]], f"must be one of {', '.join(FIELDS)}")
        ref = self.alpha_l
        new = {k: _constant(k, v, self.batch_size, ref.dtype, ref.device) for k, v in values.items()}
        return dataclasses.replace(self, **new)

    def as_dict(self) -> dict[str, list]:
        """Python lists (JSON-ready, e.g. for metrics.json); laser_angle_rad is a list of [n_u, n_v] pairs."""
        return {k: getattr(self, k).detach().cpu().double().tolist() for k in FIELDS}


# The largest photon-noise factors a fixed scene takes: c1, the signal-proportional relative std, at most 100 %
# (the robustness stages go to 20 %, training to 25 %); c2, the Poisson std's modulation, at most 10 (the
# calibration's 0.9..1.1; 10 is a hundred times the shot-noise variance).
NOISE_MAX: dict[str, float] = {"c1": 1.0, "c2": 10.0}


def _constant(key: str, value: Any, batch: int, dtype: torch.dtype, device) -> torch.Tensor:
    """A (B,) or (B, 2) tensor holding ``value`` (a number; a number or (n_u, n_v) pair for the angle)."""
    if isinstance(value, torch.Tensor):
        want = (batch, 2) if key == "laser_angle_rad" else (batch,)
        if value.dim() == 0:
            value = value.item()
        elif tuple(value.shape) == want:
            return value.to(device=device, dtype=dtype)
        elif key == "laser_angle_rad" and tuple(value.shape) == (2,):
            value = value.tolist()
        else:
            raise ConfigError(key, tuple(value.shape), f"a tensor value must have shape {want}")
    if key == "laser_angle_rad":
        pair = list(value) if isinstance(value, Sequence) and not isinstance(value, str) else [value, value]
        if len(pair) != 2:
            raise ConfigError(key, value, "must be a number or an (n_u, n_v) pair in radians")
        pair = [require_number(key, v) for v in pair]
        return torch.tensor(pair, dtype=dtype, device=device).expand(batch, 2).clone()
    # every scalar field is a physical, non-negative quantity; a zero exposure would make the sensor blind (the
    # sampled exposures are clipped up to data.params.exposure_min_s > 0 for the same reason); the noise factors
    # are bounded (NOISE_MAX: c2=1e9 was simulated, its image all noise)
    v = require_number(key, value, lo=0.0, lo_open=key == "exposure_s", hi=NOISE_MAX.get(key))
    return torch.full((batch,), v, dtype=dtype, device=device)


def _batch(batch: int) -> int:
    return require_number("batch", batch, lo=1, integer=True)


def _checked_inputs(batch, generator, params, *lengths_m) -> tuple[int, ParamConfig, tuple[float, ...]]:
    """sample_scene_params' arguments checked before any draw: the batch, the ranges (None: the paper's), the
    sensor's width and height and the focal length (each > 0)."""
    batch = _batch(batch)
    pc = ParamConfig() if params is None else params
    if not isinstance(pc, ParamConfig):
        raise ConfigError("params", params, "must be a ParamConfig (ParamConfig.from_config of the data.params "
                          "block) or None")
    names = ("sensor_width_m", "sensor_height_m", "focal_length_m")
    lengths = tuple(require_number(n, v, lo=0, lo_open=True) for n, v in zip(names, lengths_m))
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator, got {type(generator).__name__}")
    return batch, pc, lengths


def sample_scene_params(batch: int, generator: torch.Generator, params: ParamConfig | None,
                        sensor_width_m: float, sensor_height_m: float, focal_length_m: float, *,
                        dtype: torch.dtype = torch.float32) -> SceneParams:
    """Draw ``batch`` scene parameter sets as in Sec. 6.2 (training distribution); returns CPU tensors.

    params: the ranges (``ParamConfig.from_config`` of the ``data.params`` block; None = paper defaults).
    sensor_width_m, sensor_height_m: W_s, H_s of the simulated sensor (m); focal_length_m: f (m).

    * alpha_l: uniform over ``alpha_l_levels`` (10,000) predetermined values ``torch.linspace(lo, hi, n)``
      over [0, 2e6]. Our reading of "10K predetermined values uniformly distributed in [0, 2e6]": an evenly
      spaced grid including both ends (step ~200), each value equally likely. ``alpha_l_spacing=log`` (not the
      paper's) spaces the levels geometrically from lo to hi (from 1, with 0 as one of them, when lo = 0): the
      linear grid puts 0.5 % of its draws at alpha_l <= 1e4, where a mask that keeps the spot small saturates
      only a few pixels, so a network trained on it has hardly seen that regime (docs/codesign.md Sec. 7).
      ``alpha_l_spacing=mixed``: half the levels linear, half log (both grids' draws, 50/50), so that the strong
      laser keeps 42 % of the draws above 5e5 (linear 75 %, log 10 %) and 32 % fall at <= 1e4 (log 63 %).
    * laser_angle_rad: independent normals per axis, mean 0, 3 sigma = 0.36 * [W_s / f, H_s / f]. The paper
      prints 0.36 * [f / W_s, f / H_s], which for Table 1 (f = 0.11 m, W_s = 18.1 mm, or 13.7 mm for the
      2532-pixel crop) is 2.2-2.9 rad, not a usable incidence angle; with W_s / f the focal-plane footprint
      f * angle stays within +-0.36 W_s of the sensor centre at 3 sigma, i.e. the laser spot lands on the
      sensor, which is what the text intends.
    * dark_current_mean_e: normal, mean mu_c = 0.002 e-, std mu_c / 2, clipped at >= 0 (a negative mean
      dark current is unphysical).
    * read_noise_mean_e ~ U[350, 400] e-, read_noise_std_e ~ U[10, 11] e-, c1 ~ U[0, 0.25], c2 ~ U[0.9, 1.1],
      alpha_b ~ U[0.3, 0.7].
    * exposure_s: normal, mean 0.1 s, std 0.01 s (0.1 x mean), clipped at >= 1e-4 s (a zero or negative
      exposure would silence the sensor).

    Reproducibility: the draws are made in the fixed order of the fields above from ``generator`` (CPU), in
    float64, then cast to ``dtype``; the same generator state gives identical parameters.
    """
    batch, pc, (w, h, f) = _checked_inputs(batch, generator, params, sensor_width_m, sensor_height_m, focal_length_m)
    g, f64 = generator, torch.float64

    def uniform(lo_hi: tuple[float, float]) -> torch.Tensor:
        lo, hi = lo_hi
        return lo + (hi - lo) * torch.rand(batch, generator=g, dtype=f64)

    grid = laser_strength_levels(pc)
    alpha_l = grid[torch.randint(pc.alpha_l_levels, (batch,), generator=g)]
    sigma = torch.tensor([w / f, h / f], dtype=f64) * (pc.angle_three_sigma_fraction / 3.0)
    angle = torch.randn(batch, 2, generator=g, dtype=f64) * sigma
    mu_c = pc.dark_current_mean_e
    dark = (mu_c + mu_c * pc.dark_current_std_fraction * torch.randn(batch, generator=g, dtype=f64)).clamp_min(0)
    read_mean = uniform(pc.read_noise_mean_range_e)
    read_std = uniform(pc.read_noise_std_range_e)
    c1 = uniform(pc.c1_range)
    c2 = uniform(pc.c2_range)
    alpha_b = uniform(pc.alpha_b_range)
    exposure = (pc.exposure_mean_s + pc.exposure_std_s * torch.randn(batch, generator=g, dtype=f64)
                ).clamp_min(pc.exposure_min_s)
    return SceneParams(alpha_l=alpha_l, alpha_b=alpha_b, laser_angle_rad=angle, c1=c1, c2=c2,
                       dark_current_mean_e=dark, read_noise_mean_e=read_mean, read_noise_std_e=read_std,
                       exposure_s=exposure).to(dtype=dtype)


# The paper's figure settings ("Qualitative evaluation of the anti-dazzle imaging", Fig. resNum): alpha_b 0.7,
# c1 20 %, c2 1.0, mu_c 0.002 e-, mu_r 390 e-, sigma_r 10.5 e-; exposure = the training mean 0.1 s; laser off
# and on axis unless overridden (rows 3-4 use alpha_l = 1e6).
FIGURE_VALUES: dict[str, float] = {
    "alpha_l": 0.0, "alpha_b": 0.7, "laser_angle_rad": 0.0, "c1": 0.20, "c2": 1.0,
    "dark_current_mean_e": 0.002, "read_noise_mean_e": 390.0, "read_noise_std_e": 10.5, "exposure_s": 0.1,
}

# The seven test strengths of the quantitative evaluation: alpha_l = {0, 10^k | k = 1..6}.
LASER_STRENGTHS: tuple[float, ...] = (0.0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6)

# Supplement, table tab:Degradation_modes ("Values of Parameter in Robustness Evaluation"). Its note fixes
# c2 = 1.0, mu_r = 390 e-, sigma_r = 10.5 e- (printed as a second "mu_r"), mu_c = 0.002 e-; the exposure is not
# given there, we use the training mean 0.1 s; the laser is on axis.
ROBUSTNESS_FIXED: dict[str, float] = {
    "laser_angle_rad": 0.0, "c2": 1.0, "dark_current_mean_e": 0.002, "read_noise_mean_e": 390.0,
    "read_noise_std_e": 10.5, "exposure_s": 0.1,
}
ROBUSTNESS_STAGES: dict[str, dict[str, float]] = {
    "E1": {"alpha_l": 0.0, "alpha_b": 0.8, "c1": 0.01},
    "E2": {"alpha_l": 3e4, "alpha_b": 0.6, "c1": 0.03},
    "M": {"alpha_l": 3e5, "alpha_b": 0.4, "c1": 0.05},
    "H1": {"alpha_l": 1e6, "alpha_b": 0.3, "c1": 0.10},
    "H2": {"alpha_l": 1.5e6, "alpha_b": 0.2, "c1": 0.20},
}


def alpha_tag(v: float) -> str:
    """Laser strength alpha_l as every key and file name writes it: 0, 1e3, 1e6, 2.5e5, 1.5 (never 1e+06)."""
    if v == 0:
        return "0"
    mantissa, exponent = f"{float(v):.6e}".split("e")
    mantissa = mantissa.rstrip("0").rstrip(".")
    return mantissa if int(exponent) == 0 else f"{mantissa}e{int(exponent)}"


def laser_preset_name(v: float) -> str:
    """The evaluation preset name of laser strength alpha_l = v: laser_0, laser_1e1 .. laser_1e6."""
    return f"laser_{alpha_tag(v)}"


# Every named preset as a complete value dict: figure, E1..H2, and laser_0, laser_1e1 .. laser_1e6 (figure
# settings with that alpha_l).
PRESETS: dict[str, dict[str, float]] = {
    "figure": dict(FIGURE_VALUES),
    **{name: {**ROBUSTNESS_FIXED, **stage} for name, stage in ROBUSTNESS_STAGES.items()},
    **{laser_preset_name(v): {**FIGURE_VALUES, "alpha_l": v} for v in LASER_STRENGTHS},
}


def preset_names() -> tuple[str, ...]:
    """The names of the fixed evaluation conditions (PRESETS), in order."""
    return tuple(PRESETS)


def fixed_scene_params(batch: int, *, dtype: torch.dtype = torch.float32,
                       device: torch.device | str | None = None, **values: Any) -> SceneParams:
    """A batch in which every parameter is a constant. Unset fields take FIGURE_VALUES (the paper's figures).

    values: any SceneParams field name -> a number (laser_angle_rad: a number or an (n_u, n_v) pair, rad).
    """
    batch = _batch(batch)
    unknown = sorted(set(values) - set(FIELDS))
    if unknown:
        raise ConfigError(unknown[0], values[unknown[0]], f"is not a scene parameter; allowed: {', '.join(FIELDS)}")
    merged = {**FIGURE_VALUES, **values}
    return SceneParams(**{k: _constant(k, merged[k], batch, dtype, device) for k in FIELDS})


def preset_params(name: str, batch: int, *, dtype: torch.dtype = torch.float32,
                  device: torch.device | str | None = None) -> SceneParams:
    """The named evaluation preset (see PRESETS) repeated ``batch`` times. Unknown name -> ConfigError."""
    if name not in PRESETS:
        raise ConfigError("preset", name, f"must be one of {', '.join(PRESETS)}")
    return fixed_scene_params(batch, dtype=dtype, device=device, **PRESETS[name])
