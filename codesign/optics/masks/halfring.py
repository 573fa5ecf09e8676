"""The five half-ring phase mask of Eq. (PhaseFunc), with learnable ring radii r_n and angles theta_n.

    phi(xi, Phi) = conv( Im(xi, Phi), Q0(xi) ),   Q0 = sum_n r_n J_0(2 pi xi r_n / W_a),
    Im = sum_{m=m_min}^{m_max} sum_n a_{m,n} sin(m_o (Phi - theta_n)) J_{m_o}(2 pi xi r_n / W_a),
    m_o = 2m + 1, a_{m,n} = 4 r_n / (m_o pi).

``conv`` is ``atan`` (atan(Im / Q0), as printed, values in [-pi/2, pi/2]) or ``atan2`` (the argument of the
complex pupil field Q0 + i Im that the half-ring design synthesizes, values in (-pi, pi]).

``harmonic_sign``: "printed" uses a_{m,n} as printed. "fourier" multiplies order m by (-1)^m: the Fourier
transform of an angular harmonic e^{i k phi} on a focal-plane ring carries (-i)^k, so a half ring (ring times a
square wave in angle) needs alternating signs across the odd orders; without them the printed sum synthesizes
mostly full rings (see docs/optics.md for what each gives).

Fast evaluation: sin(m_o (Phi - theta_n)) = sin(m_o Phi) cos(m_o theta_n) - cos(m_o Phi) sin(m_o theta_n), so
    Im = sum_m [ sin(m_o Phi) A_m(xi) - cos(m_o Phi) B_m(xi) ],
    A_m = sum_n a_{m,n} cos(m_o theta_n) J_{m_o}(x_n),  B_m = sum_n a_{m,n} sin(m_o theta_n) J_{m_o}(x_n):
Bessel functions are needed only as radial profiles, and the angular harmonics sin/cos(m_o Phi) are fixed per grid.
Strategies: ``exact`` evaluates the profiles at the grid's distinct radii (exact, ~17x fewer points than pixels
for large grids) and the angular sums on one eighth of the grid (``OctantSums``); ``table`` on a uniform radial
table of ``table_size`` points with linear interpolation; ``direct`` evaluates every Bessel function at every
pixel (the reference, for tests and benchmarks).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import torch

from codesign.errors import (
    ConfigError,
    require_choice,
    require_list,
    require_number,
    require_numbers,
)
from codesign.optics.atan2 import atan_of_ratio
from codesign.optics.bessel import bessel_mix
from codesign.optics.grid import PupilGrid
from codesign.optics.masks.base import Mask, MaskSpec

PUBLISHED_R = (13.6, 91.8, 6.3, 10.3, 4.2)
PUBLISHED_THETA = (1.86, 1.09, 1.15, 1.21, 1.22)
PRESETS = {"published": (PUBLISHED_R, PUBLISHED_THETA)}
CONVENTIONS = ("atan", "atan2")
STRATEGIES = ("exact", "table", "direct")
HARMONIC_SIGNS = ("printed", "fourier")
_HARMONIC_CACHE_BYTES = 256 * 2**20  # cache sin/cos(m_o Phi) on the support up to this size


@dataclass(frozen=True)
class HalfRingSpec(MaskSpec):
    """preset: published (r_n = [13.6, 91.8, 6.3, 10.3, 4.2] lambda f / W_a, theta_n = [1.86, 1.09, 1.15, 1.21, 1.22]
    rad) or null to give r, theta; rings: with preset, r and theta null, this many rings at a plain start (r
    geometric from 4 to 90, theta 1.2 rad: a search's start 0); m_range: [m_min, m_max], orders m_o = 2m + 1 (as
    written: 3..35; [0, 17] adds the first order); convention: atan2 (argument of the complex pupil field) | atan
    (as printed); harmonic_sign: printed | fourier ((-1)^m per order: true half rings); strategy: exact (distinct
    radii) | table (radial table, linear interpolation) | direct (reference); table_size; r_bounds: the box of r
    that project() clamps into and a search explores (units of lambda f / W_a; the 640-sample window's half-width
    is ~95 such units: rings beyond it send light out of the window)."""

    kind: str = "halfring"
    preset: str | None = "published"
    r: tuple | None = None
    theta: tuple | None = None
    rings: int | None = None
    m_range: tuple = (1, 17)
    convention: str = "atan2"
    harmonic_sign: str = "printed"
    strategy: str = "exact"
    table_size: int = 4096
    r_bounds: tuple = (0.5, 100.0)


class OctantSums:
    """The angular sums of a centred square grid on one octant, 0 <= Phi_r <= pi / 4 (Phi_r = atan2(min, max) of
    |u|, |v|), and every support sample's Im from its octant's four sums, exactly.

    For odd orders m_o = 2m + 1 the eight images of Phi_r under the grid's symmetries only flip the signs of
    sin / cos(m_o Phi) or swap them (with (-1)^m): with P = sum_m sin(m_o Phi_r) A_m, Q = sum_m cos(m_o Phi_r) B_m,
    P' = sum_m (-1)^m cos(m_o Phi_r) A_m and Q' = sum_m (-1)^m sin(m_o Phi_r) B_m,
        |u| <= |v|: Im = s_u P - s_v Q,     |u| > |v|: Im = s_u P' - s_v Q',    s_u = sign(u), s_v = sign(v)
    (a zero coordinate counts as positive; where it matters both formulas agree). Four sums over 1/8 of the samples
    replace two over all of them: 4x fewer multiply-adds, and the radial profiles are gathered 8x less."""

    def __init__(self, grid: PupilGrid, orders: torch.Tensor):
        dtype, device = grid.rho.dtype, grid.rho.device
        k = torch.arange(grid.n, device=device) - grid.n // 2
        iv = k[:, None].expand(grid.n, grid.n).reshape(-1)[grid.support]  # rows: v
        iu = k[None, :].expand(grid.n, grid.n).reshape(-1)[grid.support]  # columns: u
        lo, hi = torch.minimum(iu.abs(), iv.abs()), torch.maximum(iu.abs(), iv.abs())
        reps, rep_of = torch.unique(hi * (grid.n + 1) + lo, return_inverse=True)
        r_hi, r_lo = reps // (grid.n + 1), reps % (grid.n + 1)
        phi_r = torch.atan2(r_lo.to(torch.float64), r_hi.to(torch.float64))
        arg = orders.to(torch.float64)[:, None] * phi_r[None, :]
        alt = torch.where((orders // 2) % 2 == 0, 1.0, -1.0).to(torch.float64)[:, None]  # (-1)^m
        sin, cos = torch.sin(arg), torch.cos(arg)
        # [s, j]: s pairs with A_m (0) or -B_m (1), j the unprimed / primed sum: [[P, P'], [-Q, -Q']] (2, 2, M, R)
        self.tables = torch.stack([torch.stack([sin, alt * cos]), torch.stack([cos, alt * sin])]).to(dtype)
        # each sample's radius index through its representative (same radius), and where its two terms come from
        first = torch.zeros(reps.numel(), dtype=torch.long, device=device)
        first.scatter_(0, rep_of, torch.arange(rep_of.numel(), device=device))
        self.rep_radius = grid.radius_index[first]
        swapped = (iu.abs() > iv.abs()).long()
        n_rep = reps.numel()
        self.index_x = rep_of + n_rep * swapped  # P or P'
        self.index_y = rep_of + n_rep * (2 + swapped)  # -Q or -Q'
        self.sign_x = torch.where(iu >= 0, 1.0, -1.0).to(dtype)
        self.sign_y = torch.where(iv >= 0, 1.0, -1.0).to(dtype)

    def im(self, prof: torch.Tensor) -> torch.Tensor:
        """Im at the support samples from the radial profiles (2M, U), A_m and -B_m interleaved, at the grid's
        distinct radii. Gathers are index_select: their backward is index_add (fast), where indexing's is an
        accumulating index_put (several times slower on a CPU)."""
        sums = _OctantSumsFn.apply(prof, self.tables, self.rep_radius).reshape(-1)  # [P, P', -Q, -Q']
        return self.sign_x * sums.index_select(0, self.index_x) + self.sign_y * sums.index_select(0, self.index_y)


class _OctantSumsFn(torch.autograd.Function):
    """sums[s, j, i] = sum_m prof[2 m + s, rep_radius[i]] tables[s, j, m, i]: the four angular sums at the octant's
    representatives, accumulated one order at a time (no (2, 2, M, R) product is ever formed: at the paper's
    sampling that temporary is 30 MB, and allocating and filling it cost more than the sums)."""

    @staticmethod
    def forward(ctx, prof: torch.Tensor, tables: torch.Tensor, rep_radius: torch.Tensor) -> torch.Tensor:
        m = tables.shape[2]
        g = prof.index_select(1, rep_radius).view(m, 2, -1)
        out = torch.zeros(tables.shape[0], tables.shape[1], tables.shape[3], dtype=prof.dtype, device=prof.device)
        for s in range(2):
            for j in range(2):
                for k in range(m):
                    out[s, j].addcmul_(g[k, s], tables[s, j, k])
        ctx.save_for_backward(tables, rep_radius)
        ctx.n_radii = prof.shape[1]
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: torch.Tensor):
        tables, rep_radius = ctx.saved_tensors
        m = tables.shape[2]
        gg = torch.empty(m, 2, tables.shape[3], dtype=grad.dtype, device=grad.device)
        for s in range(2):
            for k in range(m):
                torch.mul(tables[s, 0, k], grad[s, 0], out=gg[k, s]).addcmul_(tables[s, 1, k], grad[s, 1])
        gprof = torch.zeros(2 * m, ctx.n_radii, dtype=grad.dtype, device=grad.device)
        return gprof.index_add_(1, rep_radius, gg.view(2 * m, -1)), None, None


def check_rings(r: Sequence, theta: Sequence, prefix: str) -> tuple[list[float], list[float]]:
    """Ring radii in (0, 1e4] (units of lambda f / W_a) and as many angles in [-1e4, 1e4] rad (an angle beyond is
    noise once multiplied by the orders m_o), as floats; ConfigError naming ``prefix.r[i]`` / ``prefix.theta[i]``."""
    r, theta = [float(v) for v in r], [float(v) for v in theta]  # numpy / torch scalars too
    if len(r) == 0 or len(r) != len(theta):
        raise ConfigError(f"{prefix}.theta", theta, f"must have the same length as {prefix}.r "
                          f"({len(r)} values) and at least one value")
    r = [require_number(f"{prefix}.r[{i}]", v, lo=0, lo_open=True, hi=1e4) for i, v in enumerate(r)]
    theta = [require_number(f"{prefix}.theta[{i}]", v, lo=-1e4, hi=1e4) for i, v in enumerate(theta)]
    return r, theta


def check_m_range(m_range: Any, prefix: str) -> tuple[int, int]:
    """[m_min, m_max]: integers, 0 <= m_min <= m_max <= 99."""
    m_range = require_list(f"{prefix}.m_range", m_range, "must be [m_min, m_max]")
    if len(m_range) != 2:
        raise ConfigError(f"{prefix}.m_range", list(m_range), "must be [m_min, m_max]")
    m_lo = require_number(f"{prefix}.m_range[0]", m_range[0], lo=0, hi=99, integer=True)
    return m_lo, require_number(f"{prefix}.m_range[1]", m_range[1], lo=m_lo, hi=99, integer=True)


def check_r_bounds(r_bounds: Any, prefix: str) -> tuple[float, float]:
    """[lo, hi] with 0 < lo < hi: the box of r."""
    allowed = "must be [lo, hi] with 0 < lo < hi"
    r_bounds = require_list(f"{prefix}.r_bounds", r_bounds, allowed)
    if len(r_bounds) != 2:
        raise ConfigError(f"{prefix}.r_bounds", list(r_bounds), allowed)
    lo, hi = (require_number(f"{prefix}.r_bounds[{i}]", v, lo=0, lo_open=True) for i, v in enumerate(r_bounds))
    if lo >= hi:
        raise ConfigError(f"{prefix}.r_bounds", list(r_bounds), allowed)
    return lo, hi


def plain_rings(n: int) -> tuple[list[float], list[float]]:
    """A plain start for ``n`` rings: radii geometric from 4 to 90 lambda f / W_a, angles 1.2 rad."""
    if n == 1:
        return [10.0], [1.2]
    return [4.0 * (90.0 / 4.0) ** (k / (n - 1)) for k in range(n)], [1.2] * n


class HalfRingMask(Mask):
    """Half-ring phase mask with learnable radii ``r`` (units of lambda f / W_a) and angles ``theta`` [rad].

    Args:
        grid: pupil grid; aperture_diameter_m: W_a [m] (the Bessel argument is 2 pi xi r_n / W_a).
        r, theta: initial ring radii and angles, equal lengths >= 1 (default: the published five rings).
        m_range: (m_min, m_max), orders m_o = 2m + 1 (default (1, 17) as written: m_o = 3..35).
        convention: "atan" or "atan2" (see module docstring).
        harmonic_sign: "printed" or "fourier" (see module docstring).
        strategy: "exact", "table" or "direct"; table_size: radial samples of the "table" strategy.
        r_bounds: (lo, hi) box that ``project()`` clamps r into; theta is wrapped into [0, 2 pi).
        levels: quantize the phase to this many levels (None: continuous).
        prefix: config key prefix used in error messages.
    Defaults: HalfRingSpec's.
    """

    kind = "halfring"
    record_values = {"r": "list", "theta": "list"}
    record_settings = ("convention", "harmonic_sign", "m_range", "r_bounds")
    Spec = HalfRingSpec
    design_energy_floor = "published"  # no half-ring mask keeps its light in the window (docs/codesign.md)

    def __init__(self, grid: PupilGrid, aperture_diameter_m: float, r: Sequence[float] = PUBLISHED_R,
                 theta: Sequence[float] = PUBLISHED_THETA, m_range: Sequence[int] = HalfRingSpec.m_range,
                 convention: str = HalfRingSpec.convention, harmonic_sign: str = HalfRingSpec.harmonic_sign,
                 strategy: str = HalfRingSpec.strategy, table_size: int = HalfRingSpec.table_size,
                 r_bounds: Sequence[float] = HalfRingSpec.r_bounds, prefix: str = "mask", levels: int | None = None):
        super().__init__(grid, levels)
        r, theta = check_rings(r, theta, prefix)
        m_lo, m_hi = check_m_range(m_range, prefix)
        self.convention = require_choice(f"{prefix}.convention", convention, CONVENTIONS)
        self.harmonic_sign = require_choice(f"{prefix}.harmonic_sign", harmonic_sign, HARMONIC_SIGNS)
        self.strategy = require_choice(f"{prefix}.strategy", strategy, STRATEGIES)
        self.table_size = require_number(f"{prefix}.table_size", table_size, lo=16, hi=2**24, integer=True)
        self.r_bounds = check_r_bounds(r_bounds, prefix)
        self.aperture_diameter_m = require_number("optics.aperture_diameter_m", aperture_diameter_m, lo=0,
                                                  lo_open=True)
        dtype, device = grid.rho.dtype, grid.rho.device
        self.r = torch.nn.Parameter(torch.tensor(r, dtype=dtype, device=device))
        self.theta = torch.nn.Parameter(torch.tensor(theta, dtype=dtype, device=device))
        self.register_buffer("orders", torch.arange(2 * m_lo + 1, 2 * m_hi + 2, 2, device=device), persistent=False)
        self.n_max = int(self.orders[-1])
        rho_s = grid.rho.reshape(-1)[grid.support]
        self._angle_s = grid.angle.reshape(-1)[grid.support]
        self._harmonics = None
        if self.strategy != "exact" and \
                2 * len(self.orders) * rho_s.numel() * rho_s.element_size() <= _HARMONIC_CACHE_BYTES:
            self._harmonics = self._angular(self._angle_s)
        if self.strategy == "exact":
            self._radii = grid.radii
            self._octants = OctantSums(grid, self.orders)
        elif self.strategy == "table":
            r_max = float(grid.radii[-1]) if grid.radii.numel() else 0.0
            self._radii = torch.linspace(0, r_max, self.table_size, dtype=dtype, device=device)
            pos = rho_s.to(torch.float64) / max(r_max, 1e-300) * (self.table_size - 1)
            i0 = pos.floor().clamp(0, self.table_size - 2)
            self._lerp_index = i0.long()
            self._lerp_frac = (pos - i0).to(dtype)
        else:
            self._radii = rho_s

    # ---- evaluation ---------------------------------------------------------------------------------------
    def _angular(self, angle: torch.Tensor) -> torch.Tensor:
        """sin(m_o Phi) and cos(m_o Phi) interleaved like the profiles (A_m pairs with sin), shape (2M, S)."""
        arg = self.orders.to(angle.dtype)[:, None] * angle[None, :]
        return torch.stack([torch.sin(arg), torch.cos(arg)], 1).flatten(0, 1)

    def radial_profiles(self, radii: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Q0(xi) of shape (U,) and the profiles (2M, U) at the radii xi [m], A_m and -B_m interleaved (row 2k:
        A of the k-th order, row 2k + 1: -B)."""
        x = (2 * math.pi / self.aperture_diameter_m) * self.r[:, None] * radii[None, :]  # (R, U)
        mo = self.orders.to(x.dtype)
        a = 4 * self.r[:, None] / (mo[None, :] * math.pi)  # (R, M)
        if self.harmonic_sign == "fourier":
            a = a * torch.where((self.orders // 2) % 2 == 0, 1.0, -1.0).to(a)  # (-1)^m, m = (m_o - 1) / 2
        ang = mo[None, :] * self.theta[:, None]
        pairs = torch.stack([a * torch.cos(ang), -a * torch.sin(ang)], 2).flatten(1)  # (R, 2M): A_m, -B_m per m
        orders = [n for n in self.orders.tolist() for _ in range(2)]
        # x's rows ascend with the radii, so the Bessel regimes are contiguous runs (see bessel_rows)
        prof = bessel_mix(x, torch.cat([self.r[:, None], pairs], 1), [0] + orders)  # sums over rings in float64
        return prof[0], prof[1:]

    def field_parts(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Real part Q0 and imaginary part Im of the synthesized pupil field at the support samples, (S,) each."""
        q0, prof = self.radial_profiles(self._radii)
        if self.strategy == "exact":
            return q0.index_select(0, self.grid.radius_index), self._octants.im(prof)
        if self.strategy == "table":
            i0, f = self._lerp_index, self._lerp_frac
            q0_s = torch.lerp(q0[i0], q0[i0 + 1], f)
            prof_s = torch.lerp(prof[:, i0], prof[:, i0 + 1], f)
        else:
            q0_s, prof_s = q0, prof
        if self._harmonics is not None:
            im = (prof_s * self._harmonics).sum(0)
        else:  # large grid: harmonics on the fly, one order at a time, to bound memory
            m = len(self.orders)
            im = torch.zeros_like(q0_s)
            for k in range(m):
                arg = float(self.orders[k]) * self._angle_s
                im = im + prof_s[2 * k] * torch.sin(arg) + prof_s[2 * k + 1] * torch.cos(arg)
        return q0_s, im

    def support_phase(self) -> torch.Tensor:
        """The phase [rad] at the support samples: the argument of the half rings' Fourier-Bessel field, by the
        mask's convention (atan2, or the published atan of the ratio)."""
        q0, im = self.field_parts()
        return torch.atan2(im, q0) if self.convention == "atan2" else atan_of_ratio(im, q0)

    @torch.no_grad()
    def project(self) -> None:
        """Clamp the radii r_n into r_bounds (units of lambda f / W_a) and wrap the angles theta_n into [0, 2 pi)."""
        self.r.clamp_(*self.r_bounds)
        self.theta.remainder_(2 * math.pi)

    def summary(self) -> dict[str, float]:
        """The parameters as scalars: r_1.. (lambda f / W_a) and theta_1.. [rad]."""
        out = {f"r_{i + 1}": float(v) for i, v in enumerate(self.r.detach().cpu())}
        out.update({f"theta_{i + 1}": float(v) for i, v in enumerate(self.theta.detach().cpu())})
        return out

    # ---- the family interface -------------------------------------------------------------------------------------
    def bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(lower, upper) of (r_1.., theta_1..): r_bounds for the radii, [0, 2 pi] rad for the angles (float64)."""
        n = self.r.numel()
        lo = torch.tensor([self.r_bounds[0]] * n + [0.0] * n, dtype=torch.float64)
        hi = torch.tensor([self.r_bounds[1]] * n + [2 * math.pi] * n, dtype=torch.float64)
        return lo, hi

    def vector_names(self) -> list[str]:
        """r_1.., then theta_1.., in ``to_vector`` order."""
        n = self.r.numel()
        return [f"r_{i + 1}" for i in range(n)] + [f"theta_{i + 1}" for i in range(n)]

    @property
    def m_range(self) -> tuple[int, int]:
        """(m_min, m_max): the harmonics whose Bessel orders m_o = 2m + 1 the series holds."""
        return (int(self.orders[0]) - 1) // 2, (int(self.orders[-1]) - 1) // 2

    def settings(self) -> dict[str, Any]:
        """Convention, harmonic sign, harmonic range and radius bounds: what fixes the phase besides r and theta."""
        return {"convention": self.convention, "harmonic_sign": self.harmonic_sign, "m_range": list(self.m_range),
                "r_bounds": list(self.r_bounds)}

    def parameter_values(self) -> dict[str, Any]:
        """The radii r (lambda f / W_a) and angles theta [rad], JSON-ready."""
        return {"r": [float(v) for v in self.r.detach().cpu()], "theta": [float(v) for v in self.theta.detach().cpu()]}

    def on_grid(self, grid: PupilGrid, aperture_diameter_m: float) -> "HalfRingMask":
        """The same mask on another pupil grid (the "exact" strategy), frozen."""
        v = self.parameter_values()
        return HalfRingMask(grid, aperture_diameter_m, v["r"], v["theta"], self.m_range, self.convention,
                            self.harmonic_sign, "exact", self.table_size, self.r_bounds, levels=self.levels).freeze()

    @classmethod
    def check_record(cls, record: Mapping[str, Any], prefix: str) -> None:
        """Check a half-ring record (mask.init=PATH) under ``prefix``: rings, harmonic range, convention, sign and
        radius bounds; ConfigError naming the key otherwise."""
        check_rings(record["r"], record["theta"], prefix)
        if "m_range" in record:
            check_m_range(record["m_range"], prefix)
        for key, choices in (("convention", CONVENTIONS), ("harmonic_sign", HARMONIC_SIGNS)):
            if key in record:
                require_choice(f"{prefix}.{key}", record[key], choices)
        if "r_bounds" in record:
            check_r_bounds(record["r_bounds"], prefix)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], grid: PupilGrid, aperture_diameter_m: float,
                    record: dict | None = None, prefix: str = "mask") -> "HalfRingMask":
        """Build from a validated ``mask`` mapping; ``record``: a loaded mask.init record of this family (its r,
        theta and settings win over the preset)."""
        preset = cfg.get("preset", HalfRingSpec.preset)
        r, theta, rings = cfg.get("r"), cfg.get("theta"), cfg.get("rings")
        if record is not None:
            if r is not None or theta is not None:
                raise ConfigError(f"{prefix}.init", cfg.get("init"), f"cannot be combined with explicit {prefix}.r / "
                                  f"{prefix}.theta; set {prefix}.init=null to use your own values")
            r, theta = record["r"], record["theta"]
        elif preset is not None:
            require_choice(f"{prefix}.preset", preset, tuple(PRESETS))
            if r is not None or theta is not None:
                raise ConfigError(f"{prefix}.preset", preset, f"cannot be combined with explicit {prefix}.r / "
                                  f"{prefix}.theta; set {prefix}.preset=null to use your own values")
            if rings is not None and rings != len(PRESETS[preset][0]):
                raise ConfigError(f"{prefix}.rings", rings, f"the {preset} preset has {len(PRESETS[preset][0])} "
                                  f"rings: set {prefix}.preset=null for another number")
            r, theta = PRESETS[preset]
        elif r is None and theta is None and rings is not None:
            r, theta = plain_rings(require_number(f"{prefix}.rings", rings, lo=1, hi=100, integer=True))
        elif r is None or theta is None:
            raise ConfigError(f"{prefix}.r", r, f"{prefix}.r and {prefix}.theta are required when {prefix}.preset "
                              f"is null (allowed presets: {', '.join(PRESETS)}), or {prefix}.rings for a plain start")
        r = require_numbers(f"{prefix}.r", r, "must be a list of ring radii (units of lambda f / W_a)")
        theta = require_numbers(f"{prefix}.theta", theta, f"must be a list of ring angles [rad], as many as {prefix}.r")
        m_range = require_list(f"{prefix}.m_range", cfg.get("m_range", HalfRingSpec.m_range), "must be [m_min, m_max]")
        r_bounds = require_list(f"{prefix}.r_bounds", cfg.get("r_bounds", HalfRingSpec.r_bounds), "must be [lo, hi] "
                                "with 0 < lo < hi")  # its length and values: the constructor
        return cls(grid, aperture_diameter_m, r, theta, m_range=tuple(m_range),
                   convention=cfg.get("convention", HalfRingSpec.convention),
                   harmonic_sign=cfg.get("harmonic_sign", HalfRingSpec.harmonic_sign),
                   strategy=cfg.get("strategy", HalfRingSpec.strategy),
                   table_size=cfg.get("table_size", HalfRingSpec.table_size), r_bounds=tuple(r_bounds),
                   prefix=prefix, levels=cfg.get("levels"))
