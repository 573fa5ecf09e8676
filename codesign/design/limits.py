"""The physical limit of the LSR / MTF trade for any phase-only mask, on a given focal window and MTF band.

For a PSF h on the m x m window holding energy E = sum h (E = 1 when the window holds the whole PSF), with
OTF = DFT(h) / E:
  Parseval    sum_f |OTF(f)|^2 = m^2 sum_x h(x)^2 / E^2 <= m^2 max(h) / E = m^2 LSR h0(0) / E,
  phase-only  |OTF(f)| <= OTF0(f): the OTF is the pupil field's normalized autocorrelation, whose modulus the
              triangle inequality bounds by the aperture's own autocorrelation (the uncoded OTF),
  and OTF(0) = 1. mtf_mean is the band mean of the radial-mean MTF: a weighted sum sum_f w_f |OTF(f)| with
  w_f = 1 / (K n_k) for a frequency f in the k-th of the K radial bins of the band (n_k frequencies in it).
Maximizing sum_f w_f M_f subject to sum_f M_f^2 <= B and 0 <= M_f <= OTF0(f) is a water-filling problem: the
optimum is M_f = min(OTF0(f), t w_f) for the level t that spends the budget B = m^2 LSR h0(0) / E - 1 (the DC term
takes 1; frequencies outside the band get nothing). Both directions are monotone in t, so
  ``mtf_bound(lsr)``   the largest mtf_mean any phase mask can have at this LSR, and
  ``lsr_limit(mtf)``   the smallest LSR any phase mask can have at this mtf_mean
are one bisection on t each. The bound needs no optimization of any mask, so it holds for every family; a mask
that lands beyond it means a broken simulation (the tests check that none does).
"""
from __future__ import annotations

import torch

from codesign.optics import RadialMTF, metrics


class MTFLimit:
    """The limit curve of an optical system's window and MTF band (see the module docstring).

    Args:
        system: OpticalSystem (its uncoded PSF gives OTF0 and h0(0)); band: (low, high] normalized frequency.
    """

    def __init__(self, system, band: tuple[float, float]):
        radial = RadialMTF(system.spec, device=system.grid.rho.device)
        with torch.no_grad():
            psf0 = system.uncoded_psf().to(torch.float64)
        self.m = system.spec.focal_n
        self.h0 = float(system.uncoded_peak)
        self.otf0 = metrics.mtf(psf0).reshape(-1).cpu()  # the uncoded OTF, |OTF0(f)|
        sel = radial.band_mask(tuple(band)).cpu()
        idx = radial.bin_index.cpu()
        in_band = sel[idx]
        weights = 1.0 / (int(sel.sum()) * radial.counts.cpu()[idx[in_band]])
        otf0 = self.otf0[in_band]
        self.uncoded_mtf_mean = float((weights * otf0).sum())
        # Exact water-filling: M_f = min(OTF0_f, t w_f) saturates at t_f = OTF0_f / w_f. Sorted by t_f, the band
        # mean and the power are sat_mean + t rest_w2 and sat_power + t^2 rest_w2 between breakpoints, where the
        # first k frequencies are saturated (cumulative sums).
        order = torch.argsort(otf0 / weights)
        w, o = weights[order], otf0[order]
        zero = torch.zeros(1, dtype=torch.float64)
        self._t = torch.cat([zero, (o / w)])                       # breakpoints, t_0 = 0
        self._sat_mean = torch.cat([zero, torch.cumsum(w * o, 0)])  # after k saturated
        self._sat_power = torch.cat([zero, torch.cumsum(o**2, 0)])
        self._rest_w2 = torch.cat([torch.cumsum((w**2).flip(0), 0).flip(0), zero])  # sum of w^2 not saturated

    def _solve(self, values: torch.Tensor, target: float, quadratic: bool) -> float:
        """The level t where ``values`` (mean or power at the breakpoints) reaches ``target``."""
        k = int(torch.searchsorted(values, torch.tensor([target], dtype=torch.float64)).item())  # first >= target
        k = max(k, 1)
        k0 = k - 1  # t lies in [t_k0, t_k): k0 saturated
        if self._rest_w2[k0] == 0:
            return float(self._t[k0])
        if quadratic:
            return float(((target - self._sat_power[k0]) / self._rest_w2[k0]).clamp_min(0).sqrt())
        return float((target - self._sat_mean[k0]) / self._rest_w2[k0])

    def _at(self, t: float) -> tuple[float, float]:
        """(mtf_mean, sum M^2 over the non-DC frequencies) of the water-filling profile at level t."""
        k = int(torch.searchsorted(self._t, torch.tensor([t], dtype=torch.float64), right=True).item()) - 1
        k = min(max(k, 0), self._rest_w2.numel() - 1)
        return (float(self._sat_mean[k] + t * self._rest_w2[k]),
                float(self._sat_power[k] + t * t * self._rest_w2[k]))

    def mtf_bound(self, lsr: float, energy: float = 1.0) -> float:
        """The largest mtf_mean a phase-only mask can reach with this LSR (window energy ``energy``)."""
        budget = self.m**2 * lsr * self.h0 / energy - 1.0
        if budget <= 0:
            return 0.0
        powers = self._sat_power + self._t**2 * self._rest_w2
        if budget >= float(powers[-1]):
            return self.uncoded_mtf_mean
        return self._at(self._solve(powers, budget, quadratic=True))[0]

    def lsr_limit(self, mtf_mean: float, energy: float = 1.0) -> float:
        """The smallest LSR any phase-only mask can have at this mtf_mean (inf above the uncoded aperture's)."""
        if mtf_mean > self.uncoded_mtf_mean:
            return float("inf")
        means = self._sat_mean + self._t * self._rest_w2
        power = self._at(self._solve(means, mtf_mean, quadratic=False))[1]
        return energy * (1.0 + power) / (self.m**2 * self.h0)

    def curve(self, mtf_means) -> list[tuple[float, float]]:
        """(mtf_mean, lsr_limit) pairs, e.g. to draw the limit on an LSR / MTF plot."""
        return [(float(v), self.lsr_limit(float(v))) for v in mtf_means]
