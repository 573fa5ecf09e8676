"""Validated trainer settings (``trainer.*``)."""
from __future__ import annotations

from dataclasses import dataclass, field

from codesign.config.store import register, spec_node
from codesign.errors import ConfigError, require_number
from codesign.spec_base import SpecMixin

MAX_STEPS = 10**7  # generator updates: 20x the paper's 500,000 (trainer=paper)


@dataclass(frozen=True)
class TrainerSpec(SpecMixin):
    """steps: generator updates; lr_weights / lr_biases: Adam learning rates (Sec. 6.2: 2e-4 / 4e-4); betas.
    Schedule (Sec. 6.2, 400 epochs: halved after 100, then "reduced by 70 percent" every 50): the learning rate
    is multiplied by ``first_factor`` at ``first_fraction`` of the steps, then by ``factor`` every
    ``every_fraction`` (defaults 0.25, 0.5, 0.125, 0.3). critic_steps: critic updates per generator update
    (on the same batch and the same generator outputs).
    grad_clip: max global gradient norm (null = off). ema: generator EMA decay (null = off).
    checkpoint_every / val_every / image_every: in steps (0 = only at the end). val_size: fixed validation batch.
    resume: checkpoint path (null = resume from the run dir's checkpoint.pt when one exists).
    time_budget_s: stop training (then checkpoint and evaluate) once this much wall time has passed; the
    schedule still refers to ``steps`` (null = no budget).
    amp: null (float32) or bf16: the networks' forward passes under bfloat16 autocast; the optics, the sensor
    simulation, the Wiener deconvolution and the losses stay in float32 (docs/scaling.md).
    channels_last: networks and their inputs in NHWC memory (faster convolutions on tensor-core GPUs).
    compile: torch.compile the generators G1 and G2 (not G_v's FFTs; not the critics, whose gradient penalty
    needs a double backward that compiled graphs do not support).
    calibrate_crops: training-split crops the restorer's fitted parts are fitted on at the end of a training
    (Restorer.calibrate, e.g. model.level_head; half of them without a laser).
    """

    steps: int = 300
    lr_weights: float = 2e-4
    lr_biases: float = 4e-4
    betas: tuple = (0.9, 0.999)
    first_fraction: float = 0.25
    first_factor: float = 0.5
    every_fraction: float = 0.125
    factor: float = 0.3
    critic_steps: int = 1
    grad_clip: float | None = None
    ema: float | None = None
    checkpoint_every: int = 100
    val_every: int = 25
    image_every: int = 100
    val_size: int = 4
    resume: str | None = None
    time_budget_s: float | None = None
    amp: str | None = None
    channels_last: bool = False
    compile: bool = False
    calibrate_crops: int = 128
    prefix: str = field(default="trainer", compare=False, repr=False)

    def __post_init__(self) -> None:
        p = self.prefix
        # bounded: 1e12 steps was accepted (while 2.5 was refused) and would never end; 20x the paper's 500k
        require_number(f"{p}.steps", self.steps, lo=1, hi=MAX_STEPS, integer=True)
        for k in ("lr_weights", "lr_biases"):
            require_number(f"{p}.{k}", getattr(self, k), lo=0, lo_open=True, hi=1)
        betas = list(self.betas) if hasattr(self.betas, "__len__") and not isinstance(self.betas, str) else None
        if betas is None or len(betas) != 2 or not all(isinstance(b, (int, float)) and 0 <= b < 1 for b in betas):
            raise ConfigError(f"{p}.betas", self.betas, "must be [beta1, beta2], each in [0, 1)")
        object.__setattr__(self, "betas", tuple(float(b) for b in betas))
        for k in ("first_fraction", "every_fraction"):
            require_number(f"{p}.{k}", getattr(self, k), lo=0, lo_open=True, hi=1)
        for k in ("first_factor", "factor"):
            require_number(f"{p}.{k}", getattr(self, k), lo=0, lo_open=True, hi=1)
        require_number(f"{p}.critic_steps", self.critic_steps, lo=1, hi=100, integer=True)
        if self.grad_clip is not None:
            require_number(f"{p}.grad_clip", self.grad_clip, lo=0, lo_open=True)
        if self.ema is not None:
            require_number(f"{p}.ema", self.ema, lo=0, lo_open=True, hi=1, hi_open=True)
        for k in ("checkpoint_every", "val_every", "image_every"):
            require_number(f"{p}.{k}", getattr(self, k), lo=0, integer=True)
        require_number(f"{p}.val_size", self.val_size, lo=1, hi=256, integer=True)
        require_number(f"{p}.calibrate_crops", self.calibrate_crops, lo=4, hi=65536, integer=True)
        if self.time_budget_s is not None:
            require_number(f"{p}.time_budget_s", self.time_budget_s, lo=0, lo_open=True)
        if self.amp not in (None, "bf16"):
            raise ConfigError(f"{p}.amp", self.amp, "must be null (float32) or bf16 (float16 would need loss "
                              "scaling; bfloat16 has float32's range)")
        for k in ("channels_last", "compile"):
            if not isinstance(getattr(self, k), bool):
                raise ConfigError(f"{p}.{k}", getattr(self, k), "must be true or false")

    def lr_factor(self, step: int) -> float:
        """Multiplier of the initial learning rates at (0-based) ``step``."""
        first = self.first_fraction * self.steps
        if step < first:
            return 1.0
        k = int((step - first) // (self.every_fraction * self.steps))
        return self.first_factor * self.factor**k


register("trainer", "default", spec_node(TrainerSpec))


@dataclass(frozen=True)
class InitSpec(SpecMixin):
    """A warm start (``init.*`` of +experiment=joint and baseline): checkpoint: a training checkpoint whose network
    weights the run starts from (trained on another mask or PSF; the same model, optics, sensor and image sizes, the
    measured-PSF keys optics.psf_* aside; 'pretrained' = the shipped restorer trained over many masks,
    codesign/models/pretrained/README.md; 'auto' = that one where it fits the run, else fresh weights; null = fresh
    weights). The mask comes from mask / mask.init, never from
    this checkpoint."""

    checkpoint: str | None = None
    prefix: str = field(default="init", compare=False, repr=False)

    def __post_init__(self) -> None:
        if self.checkpoint is not None and not isinstance(self.checkpoint, str):
            raise ConfigError(f"{self.prefix}.checkpoint", self.checkpoint, "must be a checkpoint path or null")


register("init", "default", spec_node(InitSpec))
