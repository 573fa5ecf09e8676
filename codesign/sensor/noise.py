"""Sensor noise terms, each with its own random stream so that skipping one never changes another.

Photon model (our reading of the paper's "omega ~ N(c1 mu_p, c2 sigma_p)", which cannot be literal: c1 = 0
would erase the signal, yet c1 is sampled in [0, 25%] as a noise strength):

    omega ~ N(mu_p, c2^2 mu_p + c1^2 mu_p^2)

i.e. Poisson shot noise in its Gaussian limit (variance mu_p = sigma_p^2) with its standard deviation modulated by
c2 (the calibration's 0.9..1.1), plus a signal-proportional term of relative standard deviation c1 (a
photo-response non-uniformity / illumination fluctuation; 1%..20% in the robustness stages). c1 = 0 and c2 = 1
give the pure shot-noise limit. Reparameterized (omega = mu + sigma * eps) so gradients reach mu, hence the PSF.
"""
from __future__ import annotations

import torch

TERMS = ("photon", "dark", "read", "quant")


def _stream_seed(seed: int, term: int) -> int:
    return (int(seed) * 1_000_003 + 7919 * (term + 1)) % (2**63 - 1)


class NoiseStreams:
    """One torch.Generator per noise term, seeded from a base seed: streams are independent of which run.

    ``seed``: one int for the whole batch, or a sequence of ints, one per sample: then every sample draws from
    its own streams, so a sample's noise does not depend on which batch (or which rank's share of a distributed
    batch) it is simulated in.
    """

    def __init__(self, seed, device: torch.device):
        self.per_sample = not isinstance(seed, int) and hasattr(seed, "__len__")
        seeds = [int(s) for s in seed] if self.per_sample else [int(seed)]
        self.gens = {}
        for i, term in enumerate(TERMS):
            self.gens[term] = [torch.Generator(device=device).manual_seed(_stream_seed(s, i)) for s in seeds]

    def _draw(self, term: str, like: torch.Tensor, draw) -> torch.Tensor:
        gens = self.gens[term]
        if not self.per_sample:
            return draw(like.shape, gens[0])
        if like.shape[0] != len(gens):
            raise ValueError(f"{len(gens)} per-sample noise seeds for a batch of {like.shape[0]}")
        return torch.cat([draw((1,) + tuple(like.shape[1:]), g) for g in gens])

    # Draws are made in float64 and cast, so a float32 run and its float64 reference see the same noise.
    def normal(self, term: str, like: torch.Tensor) -> torch.Tensor:
        """Standard normal draws of noise ``term``, shaped and typed like ``like`` (drawn in float64)."""
        return self._draw(term, like, lambda shape, g: torch.randn(
            shape, generator=g, dtype=torch.float64, device=like.device)).to(like.dtype)

    def uniform(self, term: str, like: torch.Tensor) -> torch.Tensor:
        """Uniform draws in [-0.5, 0.5) of noise ``term``, shaped and typed like ``like`` (drawn in float64)."""
        return (self._draw(term, like, lambda shape, g: torch.rand(
            shape, generator=g, dtype=torch.float64, device=like.device)) - 0.5).to(like.dtype)

    def poisson(self, term: str, rate: torch.Tensor) -> torch.Tensor:
        """Poisson counts of mean ``rate`` from noise ``term``'s stream (per sample when seeded per sample)."""
        if not self.per_sample:
            return torch.poisson(rate, generator=self.gens[term][0])
        if rate.shape[0] != len(self.gens[term]):
            raise ValueError(f"{len(self.gens[term])} per-sample noise seeds for a batch of {rate.shape[0]}")
        return torch.cat([torch.poisson(rate[i:i + 1], generator=g) for i, g in enumerate(self.gens[term])])


def photons(mu: torch.Tensor, c1: torch.Tensor, c2: torch.Tensor, scale: float, streams: NoiseStreams,
            skip: bool = True) -> torch.Tensor:
    """Gaussian photon count with mean ``mu`` (B,1,H,W) and std sqrt(c2^2 mu + c1^2 mu^2) * scale.

    ``scale`` = sqrt(sum w^2) of the binning that maps sensor pixels to a simulated pixel (1 at sensor resolution).
    Skipped (exactly mu) when every c1 and c2 in the batch is zero.
    """
    if skip and not bool((c1 != 0).any() or (c2 != 0).any()):
        return mu
    var = c2**2 * mu + c1**2 * mu**2
    # d sqrt(var) / d mu is infinite at var = 0 (a black pixel or c1 = c2 = 0): there the std is exactly 0 and so
    # is its gradient, which the clamp inside the where keeps finite.
    std = torch.where(var > 0, torch.sqrt(var.clamp_min(torch.finfo(var.dtype).tiny)), torch.zeros_like(var))
    return mu + std * scale * streams.normal("photon", mu)


def dark_current(mean_e: torch.Tensor, like: torch.Tensor, n_eff: float, streams: NoiseStreams,
                 skip: bool = True) -> torch.Tensor | None:
    """Poisson dark electrons per sensor pixel, averaged over n_eff pixels: Poisson(n_eff mu_c) / n_eff; None if 0."""
    if skip and not bool((mean_e != 0).any()):
        return None
    rate = (mean_e * n_eff).expand_as(like).to(torch.float64).contiguous()
    return (streams.poisson("dark", rate) / n_eff).to(like.dtype)


def read_noise(mean_e: torch.Tensor, std_e: torch.Tensor, like: torch.Tensor, scale: float,
               streams: NoiseStreams, skip: bool = True) -> torch.Tensor:
    """Gaussian read noise N(mu_r, (sigma_r * scale)^2); the random draw is skipped when every sigma_r is 0."""
    if skip and not bool((std_e != 0).any()):
        return mean_e.expand_as(like)
    return mean_e + std_e * scale * streams.normal("read", like)


def round_ste(x: torch.Tensor) -> torch.Tensor:
    """Round to nearest with a straight-through gradient (d round(x) / dx taken as 1)."""
    return x + (torch.round(x) - x).detach()
