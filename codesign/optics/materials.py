"""Refractive index of a mask material at any wavelength, from the dispersion formula of a named preset
(conf/material/*.yaml: the coefficients and their source) or a constant.

The index matters twice: a surface step h gives the phase 2 pi (n(lambda) - 1) h / lambda, so the depth of a
2 pi step at the design wavelength is lambda / (n - 1); and a laser at another wavelength sees the same heights
with another n and another lambda (tolerance analysis: wavelength detuning).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

from codesign.config.store import document
from codesign.errors import ConfigError, require_choice, require_list, require_number
from codesign.spec_base import SpecMixin

log = logging.getLogger("codesign.optics")

FORMULAS = ("sellmeier", "cauchy", "constant")
# The highest refractive index of a transparent optical material: germanium's ~4 in the infrared (silicon ~3.5,
# the visible's highest, e.g. rutile, below 3); an index of 1e6 made a 2 pi step a millionth of a wavelength deep.
MAX_INDEX = 5.0
INDEX_RANGE = f"a mask material needs 1 < n <= {MAX_INDEX:g} (no optical material has more: germanium, ~4 in the " \
              f"infrared, is the highest)"
_COEFF_ALLOWED = {
    "sellmeier": "must be a list of [B_i, lambda_i_um] pairs: n^2 - 1 = sum B_i lambda^2 / (lambda^2 - lambda_i^2), "
                 "lambda in um",
    "cauchy": "must be a list of coefficients [A, B, C, ...]: n = A + B / lambda^2 + C / lambda^4 + ..., lambda in um",
    "constant": "must be [n]: one index at every wavelength",
}


@dataclass(frozen=True)
class Material(SpecMixin):
    """A mask material. name: a label; formula: sellmeier | cauchy | constant; coefficients: see _COEFF_ALLOWED;
    valid_um: [low, high] wavelength range of the fit in um (a wavelength outside it is used with a warning);
    source: where the coefficients come from."""

    name: str = "fused_silica"
    formula: str = "sellmeier"
    coefficients: tuple = ((0.6961663, 0.0684043), (0.4079426, 0.1162414), (0.8974794, 9.896161))
    valid_um: tuple = (0.21, 3.71)
    source: str = "Malitson, J. Opt. Soc. Am. 55, 1205 (1965)"
    prefix: str = field(default="material", compare=False, repr=False)

    def __post_init__(self) -> None:
        p = self.prefix
        if not isinstance(self.name, str) or not self.name:
            raise ConfigError(f"{p}.name", self.name, "must be a non-empty label")
        require_choice(f"{p}.formula", self.formula, FORMULAS)
        allowed = _COEFF_ALLOWED[self.formula]
        coeffs = require_list(f"{p}.coefficients", self.coefficients, allowed)
        if not coeffs:
            raise ConfigError(f"{p}.coefficients", coeffs, allowed)
        if self.formula == "sellmeier":
            out = []
            for i, pair in enumerate(coeffs):
                pair = require_list(f"{p}.coefficients[{i}]", pair, allowed)
                if len(pair) != 2:
                    raise ConfigError(f"{p}.coefficients[{i}]", pair, allowed)
                out.append((require_number(f"{p}.coefficients[{i}][0]", pair[0]),
                            require_number(f"{p}.coefficients[{i}][1]", pair[1], lo=0)))
            coeffs = tuple(out)
        else:
            if self.formula == "constant" and len(coeffs) != 1:
                raise ConfigError(f"{p}.coefficients", coeffs, allowed)
            coeffs = tuple(require_number(f"{p}.coefficients[{i}]", c) for i, c in enumerate(coeffs))
            if self.formula == "constant" and coeffs[0] > MAX_INDEX:  # n <= 1 is named with the wavelength by index()
                raise ConfigError(f"{p}.coefficients", list(coeffs), f"give n = {coeffs[0]:g} at every wavelength: "
                                  f"{INDEX_RANGE}")
        object.__setattr__(self, "coefficients", coeffs)
        lo_hi = require_list(f"{p}.valid_um", self.valid_um, "must be [low, high] in um with 0 < low < high")
        if len(lo_hi) != 2 or not 0 < require_number(f"{p}.valid_um[0]", lo_hi[0]) < \
                require_number(f"{p}.valid_um[1]", lo_hi[1]):
            raise ConfigError(f"{p}.valid_um", list(lo_hi), "must be [low, high] in um with 0 < low < high")
        object.__setattr__(self, "valid_um", (float(lo_hi[0]), float(lo_hi[1])))
        if not isinstance(self.source, str) or not self.source.strip():
            raise ConfigError(f"{p}.source", self.source, "must say where the coefficients come from")

    def index(self, wavelength_m: float) -> float:
        """n at ``wavelength_m`` (vacuum wavelength, m)."""
        lam = wavelength_m * 1e6
        if self.formula == "constant":
            n = self.coefficients[0]
        elif self.formula == "cauchy":
            n = sum(c / lam ** (2 * i) for i, c in enumerate(self.coefficients))
        else:
            n2 = 1 + sum(b * lam**2 / (lam**2 - l0**2) for b, l0 in self.coefficients)
            n = math.sqrt(n2) if n2 > 0 else float("nan")
        if not (math.isfinite(n) and n > 1):
            raise ConfigError(f"{self.prefix}.coefficients", list(self.coefficients),
                              f"give n = {n:.6g} at {lam:.4g} um: a mask material needs n > 1")
        if n > MAX_INDEX:
            raise ConfigError(f"{self.prefix}.coefficients", list(self.coefficients),
                              f"give n = {n:.6g} at {lam:.4g} um: {INDEX_RANGE}")
        return float(n)

    def check_wavelength(self, wavelength_m: float) -> None:
        """Warn when the design wavelength lies outside the fit's range."""
        lam = wavelength_m * 1e6
        if not self.valid_um[0] <= lam <= self.valid_um[1]:
            log.warning("material %s: %.4g um is outside its fit's range %.4g-%.4g um (%s); n = %.5f is an "
                        "extrapolation", self.name, lam, *self.valid_um, self.source, self.index(wavelength_m))

    def summary(self, wavelength_m: float) -> dict:
        """The material's name, formula, source and refractive index at ``wavelength_m`` [m], for metrics.json."""
        return {"material": self.name, "material_formula": self.formula, "material_source": self.source,
                "refractive_index": self.index(wavelength_m)}


# the options material=NAME are conf/material/*.yaml; their keys are these fields (docs/config.md)
document("material", Material)
