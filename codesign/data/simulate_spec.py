"""The validated ``simulate`` block of +experiment=simulate: which test scenes are imaged at which laser strengths,
under which fixed scene parameters (the paper's figure settings unless overridden)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from codesign.config.store import register, spec_node
from codesign.data.params import FIGURE_VALUES, LASER_STRENGTHS, fixed_scene_params
from codesign.errors import ConfigError, refuse_repeats, require_number, require_numbers
from codesign.spec_base import SpecMixin

MAX_ANGLE = round(math.pi / 2, 4)  # rad


@dataclass(frozen=True)
class SimulateSpec(SpecMixin):
    """scenes: the first N scenes of the test split; laser_strengths: the laser strengths alpha_l imaged (the
    paper's evaluation strengths, as evaluate.laser_strengths); laser_angle_rad: the laser's incidence (n_u, n_v)
    [rad] (focal offset f * n: (0.88, -1.32) mm; |n| <= pi / 2); params: the fixed scene parameters, by default
    the paper's figure settings (codesign/data/params.py FIGURE_VALUES, supplement Sec. 3);
    timing_repeats: batches timed for the images-per-second figure."""

    scenes: int = 3
    laser_strengths: tuple = LASER_STRENGTHS
    laser_angle_rad: tuple = (0.008, -0.012)
    params: dict = field(default_factory=lambda: {k: v for k, v in FIGURE_VALUES.items()
                                                  if k not in ("alpha_l", "laser_angle_rad")})
    timing_repeats: int = 3
    prefix: str = field(default="simulate", compare=False, repr=False)

    def __post_init__(self) -> None:
        p = self.prefix
        put = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731
        put("scenes", require_number(f"{p}.scenes", self.scenes, lo=1, hi=64, integer=True))
        put("laser_strengths", tuple(require_numbers(f"{p}.laser_strengths", self.laser_strengths,
                                                     "must be a non-empty list of laser strengths >= 0", lo=0,
                                                     hi=1e12)))
        if not self.laser_strengths:
            raise ConfigError(f"{p}.laser_strengths", [], "must be a non-empty list of laser strengths >= 0")
        refuse_repeats(f"{p}.laser_strengths", self.laser_strengths)  # each would be simulated again
        # an incidence beyond 90 degrees from the axis never reaches the aperture
        put("laser_angle_rad", tuple(require_numbers(f"{p}.laser_angle_rad", self.laser_angle_rad,
                                                     "must be [n_u, n_v] in radians", 2, lo=-MAX_ANGLE,
                                                     hi=MAX_ANGLE)))
        put("timing_repeats", require_number(f"{p}.timing_repeats", self.timing_repeats, lo=1, integer=True))
        fixed = self.params if self.params is not None else {}
        if not isinstance(fixed, dict):
            raise ConfigError(f"{p}.params", fixed, "must be a mapping of scene parameters "
                              f"({', '.join(FIGURE_VALUES)})")
        for key, own in (("alpha_l", "laser_strengths"), ("laser_angle_rad", "laser_angle_rad")):
            if key in fixed:  # swept / set by their own simulate.* keys
                raise ConfigError(f"{p}.params.{key}", fixed[key], f"is set by {p}.{own}, not here")
        try:  # the fixed scene parameters, checked now rather than after the PSF is computed
            fixed_scene_params(1, **fixed)
        except ConfigError as err:
            raise ConfigError(f"{p}.params.{err.key}", err.value, err.allowed) from None
        put("params", dict(fixed))


register("simulate", "default", spec_node(SimulateSpec))
