"""Online training data: scenes -> sensor simulator (current mask) -> (sensor, I_b, b) batches, and the OTF.

One object owns everything random about the data (scene crops, scene parameters, noise seeds) so that the
trainer can checkpoint and restore it exactly.
"""
from __future__ import annotations

import torch
from omegaconf import DictConfig

from codesign.data.params import preset_params, sample_scene_params
from codesign.data.scenes import SceneSampler, build_scene_sampler, build_scene_source
from codesign.engine.distributed import SINGLE, DistContext
from codesign.engine.simulate_task import build_simulator
from codesign.errors import ConfigError
from codesign.models.wiener import otf_from_kernel
from codesign.sensor.simulator import mask_state_key, psf_state


def check_padding(sim) -> None:
    """The padded grid must hold the field plus the PSF's reach, or the (circular) Wiener deconvolution of G_v
    and of the baselines wraps the blur of one border onto the other."""
    s, k = sim.sensor, sim.coarse.ksize
    need = s.image_size + k - 1
    if s.padded_size < need:
        raise ConfigError("data.padded_size", s.padded_size, f"must be >= data.image_size + PSF kernel - 1 = "
                          f"{s.image_size} + {k} - 1 = {need} at this pitch, so that deconvolution does not wrap")


def mask_psf(system, mask, sim, device, phase: torch.Tensor | None = None):
    """(PSF state, network-pitch kernel, OTF on the padded grid) of the mask's current parameters; all three carry
    the mask's graph when gradients are enabled and its parameters require them. ``phase``: the mask's phase when
    the caller computed it (through a DistributedDataParallel wrapper of the mask)."""
    state = psf_state(system, mask.phase() if phase is None else phase)
    kernel = sim.kernel(state)
    return state, kernel, otf_from_kernel(kernel, sim.sensor.padded_size).to(device)


def frozen_psf(system, mask, sim, device):
    """mask_psf without gradient: for a frozen mask."""
    with torch.no_grad():
        return mask_psf(system, mask, sim, device)


def _to_device(x: torch.Tensor, device: torch.device) -> torch.Tensor:
    if device.type == "cuda" and x.device.type == "cpu":
        return x.pin_memory().to(device, non_blocking=True)
    return x.to(device)


class RestorationData:
    """Simulated training / validation / evaluation batches for a frozen mask.

    Batch dict: sensor (B,1,P,P) normalized input, irradiance (B,1,P,P) target I_b, scene (B,1,P,P) target b,
    saturated and laser maps (B,1,n,n). P = data.padded_size, n = data.image_size.

    ``dist``: under torchrun a training batch is this rank's share of the global batch of data.batch_size (see
    codesign/engine/distributed.py); validation and evaluation batches are whole (rank 0 runs those).
    """

    def __init__(self, cfg: DictConfig, device: torch.device, seed: int, dist: DistContext = SINGLE):
        self.cfg, self.device, self.seed, self.dist = cfg, device, seed, dist
        self.system, self.mask, self.sim = build_simulator(cfg, device, torch.float32)
        check_padding(self.sim)
        self.source = build_scene_source(cfg.data)
        self.scene_gen = torch.Generator().manual_seed(seed)
        self.param_gen = torch.Generator().manual_seed(seed + 1)
        self.sampler = build_scene_sampler(cfg.data, "train", self.scene_gen, crop_size=self.sim.scene_size,
                                           source=self.source)
        if self.sampler.batch_size % dist.world:
            raise ConfigError("data.batch_size", self.sampler.batch_size, f"must be divisible by the number of "
                              f"processes ({dist.world}): it is the global batch, split evenly across the ranks")
        self._psf = None
        self.refresh_psf()

    # ---- the optics -----------------------------------------------------------------------------------------
    def refresh_psf(self) -> None:
        """Recompute the PSF state, kernel and OTF of the mask's current parameters (no gradient)."""
        state, kernel, otf = frozen_psf(self.system, self.mask, self.sim, self.device)
        with torch.no_grad():
            key = mask_state_key(self.mask)
        self._psf = (state, kernel, otf, key)

    def invalidate_psf(self) -> None:
        """The mask has changed: recompute the frozen PSF on next use."""
        self._psf = None

    def _frozen(self, i: int):
        if self._psf is None:
            self.refresh_psf()
        return self._psf[i]

    state = property(lambda self: self._frozen(0), doc="PSFState of the current mask (no gradient)")
    kernel = property(lambda self: self._frozen(1), doc="network-pitch PSF kernel of the current mask")
    otf = property(lambda self: self._frozen(2), doc="OTF on the padded grid of the current mask")
    key = property(lambda self: self._frozen(3), doc="cache key of the current mask's parameter values")

    @property
    def padded_size(self) -> int:
        return self.sim.sensor.padded_size

    @property
    def image_size(self) -> int:
        return self.sim.sensor.image_size

    # ---- batches --------------------------------------------------------------------------------------------
    def simulate(self, scenes: torch.Tensor, params, seed: int, state=None) -> dict:
        """Simulate a batch through the current mask's frozen PSF (no gradient, kernels cached), or through
        ``state``, a PSFState carrying the mask's graph (gradient kept, kernels recomputed)."""
        # the parameters stay on the host, where the simulator makes its decisions; the scenes go to the device
        # from page-locked memory without waiting for it
        params = params.to(dtype=torch.float32)
        scenes = _to_device(scenes, self.device)
        if state is None:
            with torch.no_grad():
                out = self.sim(scenes, params, self.state, seed=seed, mask_key=self.key)
        else:
            out = self.sim(scenes, params, state, seed=seed, mask_key=None)
        out["read_noise_mean_e"] = params.read_noise_mean_e  # the black level a classical pipeline subtracts
        return out

    def _params(self, batch: int, generator: torch.Generator):
        side = self.sim.sensor.side_m
        return sample_scene_params(batch, generator, self.cfg.data.params, sensor_width_m=side,
                                   sensor_height_m=side, focal_length_m=self.sim.optics.focal_length_m)

    def train_draw(self, step: int) -> tuple:
        """(scenes, parameters, noise seeds) of training step ``step``: random crops, Sec. 6.2 parameters and one
        noise seed per sample. Under torchrun the whole global batch is drawn on every rank (scalars) and this
        rank's share simulated, so the batches do not depend on the number of processes."""
        b = self.sampler.batch_size
        part = self.dist.shard(b)
        scenes = self.sampler.sample(part)
        params = self._params(b, self.param_gen).part(part)
        base = (self.seed * 1_000_003 + step) * 65_536
        return scenes, params, [base + i for i in range(b)[part]]

    def train_batch(self, step: int) -> dict:
        """The batch of training step ``step`` (see train_draw)."""
        return self.simulate(*self.train_draw(step))

    def validation_batch(self, size: int) -> dict:
        """A fixed batch from the training distribution (own generators: independent of training's draws)."""
        gen = torch.Generator().manual_seed(self.seed + 7919)
        sampler = SceneSampler(self.source, "train", self.sim.scene_size, size, gen, flips=self.sampler.flips)
        scenes = sampler.sample()
        return self.simulate(scenes, self._params(size, gen), seed=self.seed + 104729)

    def preset_batch(self, scenes: torch.Tensor, preset: str, seed: int, **overrides) -> dict:
        """Evaluation batch: every scene under the named preset (laser_1e3, E1, ...), optional overrides."""
        params = preset_params(preset, scenes.shape[0])
        if overrides:
            params = params.replace(**overrides)
        return self.simulate(scenes, params, seed=seed)

    # ---- checkpointing of the random state ------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"scene_gen": self.scene_gen.get_state(), "param_gen": self.param_gen.get_state(), "seed": self.seed}

    def load_state_dict(self, state: dict) -> None:
        self.seed = int(state["seed"])  # the noise of step k is seeded from (seed, k)
        self.scene_gen.set_state(state["scene_gen"])
        self.param_gen.set_state(state["param_gen"])
