"""The Python API's argument checks (codesign/api.py): each argument checked as the command line checks the key it
stands for, a wrong one a ConfigError naming the function and the argument (``sensor_image seed``), the value and
what is allowed, before any work. Without them an object of the wrong kind was an AttributeError from deep inside,
a number out of range was accepted (seed=-5, scene=-1) or failed in the simulation (alpha_l=1e300), an override
that is not a string a Hydra parse error, and an empty run_dir wrote into the current directory."""
from __future__ import annotations

import os
import re
import warnings
from typing import Any, Sequence

import numpy as np
import torch
from omegaconf import DictConfig

from codesign.config.runtime import resolve_device
from codesign.data.params import fixed_scene_params
from codesign.data.simulate_spec import MAX_ANGLE
from codesign.errors import ConfigError, require_number, require_numbers
from codesign.io.captures import saturation_note

# the experiments train_restorer runs: the ones that train a restoration network
TRAINING = ("baseline", "joint")
# one Hydra override 'key=value' ('+key=value', '++key=value'): the shape of each token of a string holding several
_OVERRIDE = re.compile(r"^[+~]{0,2}[A-Za-z_][\w.@/\-]*=")
# the largest colour channels a restorer takes (model.channels' bound)
MAX_CHANNELS = 16


class Shown:
    """A value as a message shows it: its repr when short, else its type (a tensor, a module)."""

    def __init__(self, value: Any):
        self.value = value

    def __repr__(self) -> str:
        text = repr(self.value)
        return text if len(text) <= 80 else f"<a {type(self.value).__name__}>"


def check_kind(where: str, value: Any, kind: type, what: str, none: str = "None") -> None:
    """``value`` None or a ``kind``; else ConfigError naming ``where`` (function and argument) with ``what`` (and
    ``none``: what None means)."""
    if value is not None and not isinstance(value, kind):
        raise ConfigError(where, Shown(value), f"must be {what} or {none}")


def check_cfg(where: str, value: Any) -> None:
    """A configuration argument: None (the default one) or a composed DictConfig, its mask block checked as the
    command line checks it before any work (compose() checks key names only: psf_and_lsr took mask.levels=1, which
    +experiment=psf refuses): the family's settings and a mask.init record, read whole."""
    check_kind(where, value, DictConfig, "a configuration (codesign.compose(...))")
    if value is None or value.get("mask") is None:
        return
    from codesign.config.runtime import to_container
    from codesign.optics.masks import check_mask_init, check_mask_settings

    mask = to_container(value.mask)
    check_mask_settings(mask)
    check_mask_init(mask, to_container(value.get("optics")) or {})


def check_seed(where: str, seed: Any) -> int | None:
    """A noise seed: None (the configuration's) or an integer in the command line's root ``seed`` range."""
    if seed is None:
        return None
    try:
        return require_number(where, seed, lo=0, hi=1e9, integer=True)
    except ConfigError as err:
        raise ConfigError(where, seed, f"{err.allowed} (the noise seed, as the command line's seed)") from None


def check_alpha(where: str, alpha_l: Any) -> float:
    """A laser strength alpha_l in simulate.laser_strengths' range."""
    try:
        return require_number(where, alpha_l, lo=0, hi=1e12)
    except ConfigError as err:
        raise ConfigError(where, alpha_l, f"{err.allowed} (the laser strength, as simulate.laser_strengths)") from None


def check_experiment(where: str, name: Any, allowed: Sequence[str] | None = None) -> str:
    """An experiment name among ``allowed`` (default: every experiment, codesign.experiments.EXPERIMENTS)."""
    from codesign.experiments import EXPERIMENTS

    allowed = tuple(allowed or EXPERIMENTS)
    if not isinstance(name, str) or name not in allowed:
        raise ConfigError(where, Shown(name), f"must be one of {', '.join(allowed)}")
    return name


def check_overrides(function: str, overrides: Sequence[Any], run: bool = False, experiment: bool = False
                    ) -> list[str]:
    """Hydra overrides, each its own string 'key=value' (or '~key'); ``run``: an API run, whose folder is its
    ``run_dir`` argument; ``experiment``: the function names the experiment (an override of either was silently
    taken or ignored)."""
    where = f"{function} override"
    for o in overrides:
        if not isinstance(o, str):
            raise ConfigError(where, Shown(o), "must be a string 'key=value' (a Hydra override as on the command "
                              "line, e.g. 'debug=smoke')")
        if sum(bool(_OVERRIDE.match(t)) for t in o.split()) > 1:
            raise ConfigError(where, o, "holds several overrides: pass each as its own string, e.g. "
                              f"{function}(..., 'debug=smoke', 'mask.levels=8')")
        if "=" not in o and not o.startswith("~"):
            path = os.sep in o or "/" in o or os.path.exists(o)
            raise ConfigError(where, o, "is not an override 'key=value'" + (
                f": the run folder is the run_dir= argument ({function}(..., run_dir=PATH))" if path else
                " (a Hydra override as on the command line, e.g. 'debug=smoke')"))
        key = o.split("=", 1)[0].lstrip("+~")
        if run and (key == "hydra.run.dir" or key.startswith("hydra.sweep")):
            raise ConfigError(where, o, f"the run folder is the run_dir= argument ({function}(..., run_dir=PATH)), "
                              "not a hydra override")
        if experiment and key == "experiment":
            raise ConfigError(where, o, f"the experiment is {function}'s own argument (run's first, compose's "
                              "experiment=), not an override")
    return list(overrides)


def check_run_dir(where: str, run_dir: Any) -> None:
    """A run folder: None (a new one under outputs/api/) or a non-empty path (an empty one is the current
    directory: the run wrote its files there)."""
    if run_dir is None:
        return
    if not isinstance(run_dir, (str, os.PathLike)):
        raise ConfigError(where, Shown(run_dir), "must be a folder path (str or os.PathLike) or None (a new folder "
                          "under outputs/api/)")
    if not str(os.fspath(run_dir)).strip():
        raise ConfigError(where, run_dir, "must not be empty (that is the current directory): give a folder path or "
                          "None (a new folder under outputs/api/)")


def check_path(where: str, value: Any, what: str) -> None:
    """A file or folder argument: a non-empty str or os.PathLike."""
    if not isinstance(value, (str, os.PathLike)) or not str(os.fspath(value)).strip():
        raise ConfigError(where, Shown(value), f"must be {what} (a str or os.PathLike)")


def check_device(where: str, device: Any) -> torch.device:
    """A device as the command line's ``device`` key takes it (resolve_device: auto, cpu, cuda, cuda:N on a
    machine that has it), or a torch.device."""
    name = str(device) if isinstance(device, torch.device) else device
    if not isinstance(name, str):
        raise ConfigError(where, Shown(device), "must be auto, cpu, cuda or cuda:N (a str or torch.device)")
    try:
        return resolve_device(name)
    except ConfigError as err:
        raise ConfigError(where, err.value, err.allowed) from None


def check_scene(where: str, scene: Any, test_names: Sequence[str], all_names: Sequence[str]) -> None:
    """A scene: an index 0..n-1 into the test split (a negative one wrapped round) or a scene's name."""
    index = isinstance(scene, (int, np.integer)) and not isinstance(scene, bool)
    if (index and 0 <= scene < len(test_names)) or (isinstance(scene, str) and scene in all_names):
        return
    raise ConfigError(where, Shown(scene), f"must be an index 0..{len(test_names) - 1} into the test split or a "
                      "scene name (codesign.scene_names(cfg, 'all'))")


def check_scene_params(function: str, values: dict[str, Any]) -> None:
    """Scene parameters as simulate.laser_angle_rad and simulate.params check them (the angle within +-pi/2 rad: an
    incidence beyond 90 degrees never reaches the aperture; the others as fixed_scene_params bounds them)."""
    values = dict(values)
    angle = values.pop("laser_angle_rad", 0.0)
    if isinstance(angle, (torch.Tensor, np.ndarray)):
        angle = angle.tolist()
    pair = angle if isinstance(angle, (list, tuple)) else [angle, angle]
    require_numbers(f"{function} laser_angle_rad", pair, "must be a number or [n_u, n_v] in radians", 2,
                    lo=-MAX_ANGLE, hi=MAX_ANGLE)
    try:
        fixed_scene_params(1, **values)
    except ConfigError as err:
        raise ConfigError(f"{function} {err.key}", err.value, err.allowed) from None


def _real_array(where: str, value: Any, what: str) -> torch.Tensor:
    """``value`` (a numpy array, tensor or nested list of real numbers) as a float64 tensor; else ConfigError."""
    if isinstance(value, (list, tuple)):
        value = np.asarray(value)
    if isinstance(value, np.ndarray):
        real = value.dtype.kind in "iuf"
    elif isinstance(value, torch.Tensor):
        real = not (value.is_complex() or value.dtype == torch.bool)
    else:
        raise ConfigError(where, Shown(value), f"must be {what}")
    if not real:
        raise ConfigError(where, f"<array of {value.dtype}>", f"must be {what} of real numbers (not complex or bool)")
    x = torch.as_tensor(value).detach().to(torch.float64)
    if not bool(torch.isfinite(x).all()):
        raise ConfigError(where, "<array with nan or inf>", f"must be {what} of finite numbers")
    return x


def check_counts(where: str, counts: Any) -> torch.Tensor:
    """A capture: (H, W) or (C, H, W) finite real counts >= 0, at least 8 x 8 px, C <= MAX_CHANNELS."""
    allowed = "must be (H, W) or (C, H, W) finite counts >= 0 of at least 8 x 8 pixels"
    x = _real_array(where, counts, "a 2-D array or tensor of sensor counts (H, W), or (C, H, W)")
    if x.dim() not in (2, 3) or min(x.shape[-2:]) < 8 or float(x.min()) < 0:
        raise ConfigError(where, tuple(x.shape), allowed)
    if x.dim() == 3 and x.shape[0] > MAX_CHANNELS:
        raise ConfigError(where, tuple(x.shape), f"(C, H, W) takes C <= {MAX_CHANNELS} colour channels (the "
                          "checkpoint's model.channels; 1 for grayscale): a stack of captures goes one at a time")
    return x


def check_capture_fits(where: str, x: torch.Tensor, channels: int, full_scale_dn: float) -> None:
    """The capture against the checkpoint: its channels; counts above the sensor's full scale warned of (they are
    clipped to it: no measurement of the scene)."""
    if x.dim() == 3 and x.shape[0] != channels:
        raise ConfigError(where, tuple(x.shape), f"the checkpoint restores (H, W) or ({channels}, H, W) captures "
                          f"(model.channels = {channels})")
    top = float(x.max())
    if top > full_scale_dn:
        warnings.warn(f"{where}: counts up to {top:.4g} DN exceed the sensor's full scale {full_scale_dn:.0f} DN "
                      "(clipped to it): are these sensor counts of this checkpoint's sensor?", stacklevel=3)
    note = saturation_note(x, full_scale_dn)
    if note:
        warnings.warn(f"{where}: {note}", stacklevel=3)


def check_images(function: str, restored: Any, scene: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """quality's images: real finite arrays; the scene radiance in [0, 1] (what PSNR's peak and SSIM's constants
    assume), a restored image outside it warned of (clipped to it for psnr and ssim)."""
    what = "an image (H, W) or (N, 1, H, W): a numpy array or tensor"
    x = _real_array(f"{function} restored", restored, what)
    y = _real_array(f"{function} scene", scene, what)
    if y.numel() and (float(y.min()) < 0 or float(y.max()) > 1):
        raise ConfigError(f"{function} scene", f"<values in [{float(y.min()):.4g}, {float(y.max()):.4g}]>",
                          "must be radiance in [0, 1] (the range psnr and ssim assume)")
    if x.numel() and (float(x.min()) < 0 or float(x.max()) > 1):
        warnings.warn(f"{function} restored: values in [{float(x.min()):.4g}, {float(x.max()):.4g}] lie outside "
                      "[0, 1], the radiance range psnr and ssim assume: clipped to it for psnr and ssim",
                      stacklevel=3)
    return x.to(torch.float32), y.to(torch.float32)
