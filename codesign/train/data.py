"""Online training data: scenes -> the camera (current mask) -> (sensor, I_b, b) batches.

One object owns everything random about the data (scene crops, scene parameters, noise seeds) so that the trainer
can checkpoint and restore it exactly. The camera it simulates through may have a frozen mask (a restorer is
trained for fixed optics) or a trainable one (co-design): then every training batch is simulated through the
mask's current parameters *with* gradient, so that one backward pass from the restoration loss reaches the mask:

    mask params -> phase -> PSF (window) -> pixel kernel -> sensor image s and OTF (both differentiable)

Targets: the scene b does not depend on the mask; the irradiance target I_b = alpha_b (b * h) does, and is
detached: it is G1's auxiliary target, and letting the mask move it would reward making the target easy to
predict rather than making the scene easy to restore (the mask is judged by the final restoration b). While the
mask is frozen (a warm-up) the batch comes from the cached no-gradient path: same draws, no optics cost.
"""
from __future__ import annotations

import torch
from omegaconf import DictConfig

from codesign.camera import Camera, build_camera
from codesign.data.params import preset_params, sample_scene_params
from codesign.data.scenes import DataConfig, SceneSampler, SceneSource, build_scene_sampler, build_scene_source
from codesign.errors import ConfigError
from codesign.train.distributed import SINGLE, DistContext


def _to_device(x: torch.Tensor, device: torch.device) -> torch.Tensor:
    if device.type == "cuda" and x.device.type == "cpu":
        return x.pin_memory().to(device, non_blocking=True)
    return x.to(device)


def build_simulated_data(cfg: DictConfig, device: torch.device, seed: int, dist: DistContext = SINGLE,
                         camera: Camera | None = None) -> "SimulatedData":
    """The SimulatedData of a composed config: through ``camera`` (default: build_camera of ``cfg``, checked first)
    on the scenes and parameters of ``cfg.data``."""
    camera = camera if camera is not None else build_camera(cfg, device, torch.float32)
    return SimulatedData(camera, DataConfig.from_config(cfg.data), device, seed, dist)


class SimulatedData:
    """Simulated training / validation / evaluation batches through ``camera``.

    Batch dict: sensor (B,1,P,P) normalized input, irradiance (B,1,P,P) target I_b, scene (B,1,P,P) target b,
    saturated and laser maps (B,1,n,n). P = data.padded_size, n = data.image_size. While the camera's mask is
    trainable, a training batch also carries ``otf`` and ``psf`` (the window PSF) with their graphs.

    ``data``: the data.* settings (scenes, batch size, flips, the Sec. 6.2 parameter ranges); ``source``: their
    SceneSource (built from ``data`` when None; pass one to share its cache). ``dist``: under torchrun a training
    batch is this rank's share of the global batch of data.batch_size (see codesign/train/distributed.py);
    validation and evaluation batches are whole (rank 0 runs those). ``build_simulated_data`` builds one from a
    composed config.
    """

    def __init__(self, camera: Camera, data: DataConfig, device: torch.device, seed: int,
                 dist: DistContext = SINGLE, source: SceneSource | None = None):
        self.device, self.seed, self.dist = device, seed, dist
        self.camera, self.params = camera, data.params
        self.camera.check_padding()
        self.source = source if source is not None else build_scene_source(data)
        self.scene_gen = torch.Generator().manual_seed(seed)
        self.param_gen = torch.Generator().manual_seed(seed + 1)
        self.sampler = build_scene_sampler(data, "train", self.scene_gen, crop_size=self.camera.scene_size,
                                           source=self.source)
        if self.sampler.batch_size % dist.world:
            raise ConfigError("data.batch_size", self.sampler.batch_size, f"must be divisible by the number of "
                              f"processes ({dist.world}): it is the global batch, split evenly across the ranks")
        self.camera.frozen_optics()
        self.pool = None  # a MaskPool (data.masks): training batches through a pool of masks, set by use_pool
        self._val_inputs: tuple | None = None  # the validation batch's scenes and parameters (validation_batch)

    @property
    def otf(self) -> torch.Tensor:
        """OTF of the camera's current mask on the padded grid (no gradient): what a restorer deconvolves with."""
        return self.camera.otf

    @property
    def padded_size(self) -> int:
        """P, the side of every batch's maps and of the OTF's grid (data.padded_size)."""
        return self.camera.padded_size

    @property
    def image_size(self) -> int:
        """n, the side of the sensor's field inside the padded maps (data.image_size)."""
        return self.camera.image_size

    # ---- batches --------------------------------------------------------------------------------------------
    def use_pool(self, pool) -> None:
        """Train over ``pool`` (codesign/train/mask_pool.py: data.masks); the configured mask keeps validation."""
        if pool is not None and self.camera.trainable:
            raise ConfigError("data.masks", pool.names, "trains a restorer over frozen masks: a mask that trains "
                              "has one optics (leave data.masks null in a joint run)")
        self.pool = pool

    def simulate(self, scenes: torch.Tensor, params, seed: int, optics=None, camera: Camera | None = None) -> dict:
        """Simulate a batch through the current mask's frozen optics (no gradient, kernels cached), or through
        ``optics`` (the camera's OpticsOutputs of a trainable mask: gradient kept, kernels recomputed); ``camera``:
        another (frozen) camera than the run's, a pool member's."""
        # the parameters stay on the host, where the simulator makes its decisions; the scenes go to the device
        # from page-locked memory without waiting for it
        params = params.to(dtype=torch.float32)
        scenes = _to_device(scenes, self.device)
        out = (camera if camera is not None else self.camera)(scenes, params, seed, optics)
        out["read_noise_mean_e"] = params.read_noise_mean_e  # the black level a classical pipeline subtracts
        out["alpha_b"] = params.alpha_b  # each scene's exposure (model.target_level=exposure moves it when used)
        return out

    def _params(self, batch: int, generator: torch.Generator, camera: Camera | None = None):
        """Sec. 6.2 parameters, the laser's spot placed over ``camera``'s sensor (default the run's)."""
        camera = self.camera if camera is None else camera
        side = camera.sensor.side_m
        return sample_scene_params(batch, generator, self.params, sensor_width_m=side,
                                   sensor_height_m=side, focal_length_m=camera.optics.focal_length_m)

    def train_draw(self, step: int, camera: Camera | None = None) -> tuple:
        """(scenes, parameters, noise seeds) of training step ``step``: random crops, Sec. 6.2 parameters and one
        noise seed per sample, for ``camera`` (a pool member's, which may image another pixel scale; default the
        run's). Under torchrun the whole global batch is drawn on every rank (scalars) and this rank's share
        simulated, so the batches do not depend on the number of processes."""
        camera = self.camera if camera is None else camera
        b = self.sampler.batch_size
        part = self.dist.shard(b)
        scenes = self.sampler.sample(part, camera.scene_size)
        params = self._params(b, self.param_gen, camera).part(part)
        base = (self.seed * 1_000_003 + step) * 65_536
        return scenes, params, [base + i for i in range(b)[part]]

    def train_batch(self, step: int) -> dict:
        """The batch of training step ``step`` (see train_draw); with the mask's graph while it trains; through
        the step's pool member, with its OTF, under data.masks."""
        if self.pool is not None:
            camera = self.pool.camera(step)
            out = self.simulate(*self.train_draw(step, camera), camera=camera)
            out["otf"] = camera.otf
            return out
        if not self.camera.trainable:
            return self.simulate(*self.train_draw(step))
        optics = self.camera.current_optics()
        out = self.simulate(*self.train_draw(step), optics=optics)
        out["irradiance"] = out["irradiance"].detach()
        out["otf"], out["psf"], out["phase"] = optics.otf, optics.state.psf, optics.phase
        return out

    def validation_batch(self, size: int) -> dict:
        """A fixed batch from the training distribution (own generators: independent of training's draws): the
        same scenes, parameters and noise every call, imaged through the camera's current mask (a joint run
        validates its network on the mask it has learned, and a resumed run sees the batch an uninterrupted one
        sees)."""
        self.validation_scenes(size)
        with torch.no_grad():
            return self.simulate(*self._val_inputs, seed=self.validation_noise_seed)

    def unlasered_batch(self, size: int) -> dict:
        """The validation batch's ``size`` scenes and parameters without the laser (alpha_l = 0; every other
        parameter as drawn from the training distribution, alpha_b among them), same noise seed: what a restorer
        fits its unlasered behaviour on (model.level_head)."""
        self.validation_scenes(size)
        scenes, params = self._val_inputs
        with torch.no_grad():
            return self.simulate(scenes, params.replace(alpha_l=0.0), seed=self.validation_noise_seed)

    @property
    def validation_noise_seed(self) -> int:
        """The noise seed of the validation batch (and of the evaluation's baseline tuning on its scenes)."""
        return self.seed + 104729

    def validation_scenes(self, size: int) -> torch.Tensor:
        """The validation batch's ``size`` scenes: fixed crops of the training split (own generator)."""
        if self._val_inputs is None or self._val_inputs[0].shape[0] != size:
            gen = torch.Generator().manual_seed(self.seed + 7919)
            sampler = SceneSampler(self.source, "train", self.camera.scene_size, size, gen, flips=self.sampler.flips)
            scenes = sampler.sample()
            self._val_inputs = (scenes, self._params(size, gen))
        return self._val_inputs[0]

    def preset_batch(self, scenes: torch.Tensor, preset: str, seed: int, **overrides) -> dict:
        """Evaluation batch: every scene under the named preset (laser_1e3, E1, ...), optional overrides."""
        params = preset_params(preset, scenes.shape[0])
        if overrides:
            params = params.replace(**overrides)
        return self.simulate(scenes, params, seed=seed)

    # ---- checkpointing of the random state ------------------------------------------------------------------
    def state_dict(self) -> dict:
        """The scene and parameter generators' states and the seed: what a checkpoint keeps to resume the draws."""
        return {"scene_gen": self.scene_gen.get_state(), "param_gen": self.param_gen.get_state(), "seed": self.seed}

    def load_state_dict(self, state: dict) -> None:
        """Restore what ``state_dict`` kept, so that a resumed run draws the batches an uninterrupted one would."""
        self.seed = int(state["seed"])  # the noise of step k is seeded from (seed, k)
        self.scene_gen.set_state(state["scene_gen"])
        self.param_gen.set_state(state["param_gen"])
