"""ModelSpec: which SGAN variant and how large, validated before any module is built.

Sizes: ``paper`` is the supplement's listing (G: C64 + ERRA 64..512 x 7 levels; D: E64-E128-E256-E512);
``cpu`` is a 4-level, 16..64-wide network that trains on two CPU cores; ``tiny`` is for tests. Any of
stem_width / widths / d_widths given explicitly overrides the size preset.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from codesign.errors import ConfigError, require_choice, require_list, require_number
from codesign.spec_base import SpecMixin

VARIANTS = ("sgan_b", "sgan_e", "sgan_f")
G1_BASES = ("sensor", "filled")
G2_BASES = ("i_b", "wiener")
G2_BASE_PADS = ("filled", "replicate")
TARGET_LEVELS = ("scene", "exposure")
SIZES: dict[str, dict] = {
    "paper": {"stem_width": 64, "widths": (64, 128, 256, 512, 512, 512, 512), "d_widths": (64, 128, 256, 512)},
    "cpu": {"stem_width": 16, "widths": (16, 32, 64, 64), "d_widths": (16, 32, 64, 64)},
    "tiny": {"stem_width": 4, "widths": (8, 8), "d_widths": (4, 8, 8, 8)},
}


def _widths(key: str, value, n_min: int) -> tuple[int, ...]:
    allowed = f"must be a list of at least {n_min} positive integers, or null for the size preset's"
    if len(require_list(key, value, allowed)) < n_min:
        raise ConfigError(key, value, allowed)
    return tuple(require_number(f"{key}[{i}]", v, lo=1, hi=4096, integer=True) for i, v in enumerate(value))


def network_name(key: str, name, default: str) -> str:
    """A network's configured name (``key``): a short identifier, or ``default`` when null."""
    if name is None:
        return default
    if not isinstance(name, str) or not name.replace("_", "").isalnum() or len(name) > 64:
        raise ConfigError(key, name, "must be a name of letters, digits and underscores (at most 64), or null")
    return name


@dataclass(frozen=True)
class ModelSpec(SpecMixin):
    """name: the network's name as configured (the model=NAME option it came from: sgan_b, sgan_b_gated, ...), in
    the logs, metrics.json (network) and figure titles; null: the variant.
    variant: sgan_b | sgan_e | sgan_f (SGAN-F: RFT blocks in G1/G2 and FTC blocks in D1/D2).
    size: paper | cpu | tiny; stem_width, widths (generator levels), d_widths (critic levels): null = preset.
    fe_features / fe_kernel: FE = C R R R with this many features and kernel (paper: 16, 5).
    attention: efficient self-attention in every generator and critic level; key_channels: d_k (paper: 8).
    gamma_init: initial learned noise power of the Wiener module.
    g2_head_layers: input layers G2 keeps per scale (paper: 2); coarse_to_fine: the fine head also sees the
    upsampled coarse estimate.
    g1_residual: G1 predicts a correction to its input, I_b^ = s + G1(s, x, y) (a global skip); g2_linear_skip:
    each G2 output adds a 1x1 convolution of its input features (a direct, linear Wiener-like readout). Neither is
    in the paper, which leaves these details open; both make the first thousand steps far more productive.
    g2_residual: G2's outputs are corrections to I_b^ (downsampled for the coarse scale), so that the untrained
    sandwich returns I_b^; g1_base: what G1's residual corrects, the sensor image (sensor) or the sensor image with
    its saturated and padded pixels filled from their surroundings (filled, codesign/models/fill.py). Both off by
    default: at the CPU budget neither keeps the network ahead of the sensor image (docs/models.md Sec. 10; the
    arms measured: docs/results_log.md).
    g2_base: what G2's residual corrects: I_b^ itself (i_b) or its classical Wiener deconvolution with the system
    OTF (wiener), whose noise-to-signal ratio is a learned scalar starting at g2_base_nsr; the untrained sandwich
    then returns the classical pipeline's image (docs/models.md Sec. 10; the arms measured: docs/results_log.md).
    laser_gate: both stages are told whether a laser is in the image, by the presence p = f / (f + f0) of
    saturated pixels (f: their fraction of the sensor's field; f0 learned, starting at laser_gate_f0): G1's
    correction is scaled by p (an unlasered image reaches G2 as measured, where G1 would otherwise apply the halo
    removal it learned from lasered batches everywhere), and with g2_base=wiener the log nsr moves from the
    learned unlasered value (p = 0, from g2_base_nsr) to a learned lasered one (p = 1, from g2_base_nsr_lasered).
    g2_gate: G2's correction is scaled by the same presence p (needs laser_gate and g2_residual): the training
    images nearly all carry a laser (alpha_l uniform on [0, 2e6]), so G2 learns corrections of lasered images only,
    and an image without saturated pixels gets the classical pipeline's image, which is what it scores best with
    at the CPU budget (docs/models.md Sec. 10; the arms measured: docs/results_log.md).
    g2_base_pad: with g2_residual, what lies outside the sensor's field (the padding of the canvas) when G2's base
    is computed from I_b^: filled (I_b^ as G1 leaves it, the push-pull fill of g1_base=filled plus G1's correction)
    or replicate (the field's border replicated, as the evaluation's classical Wiener pads): the Wiener base of the
    main job's designed spline without a laser scores 30.80 dB after the match on the filled padding and 31.78 on
    the replicated one (docs/models.md Sec. 13).
    g2_base_nsr_tuned: with g2_base=wiener, a run from fresh weights first sets the unlasered nsr (g2_base_nsr's
    parameter) to the value of the evaluation's Wiener grid whose restorations of training-split crops without a
    laser score best after the gain/offset match, as the classical floor is tuned (codesign/train/base_tuning.py):
    the right nsr depends on the mask, and 0.03 is the published mask's (the +experiment=joint main job sets it).
    g1_halo: G1 takes a fourth channel, where the laser's light lies: the system PSF spread over the saturated pixels,
    in decades below its peak (codesign/models/sandwich.py halo_map). Without it G1 sees the mask only through the
    image, and a G1 trained over many masks (data.masks) learns their average halo (docs/models.md Sec. 11).
    level_head: the output is multiplied by a gain per image that brings it to the scene's level, estimated from
    the output's histogram by a head fitted at the end of training on training-split crops (codesign/models/level.py;
    the background strength alpha_b scales what the sensor sees and is known to no method: docs/models.md Sec. 12).
    target_level: what G2's reconstruction and adversarial terms compare its output with: the scene b (scene, the
    paper's) or the scene at the exposure the sensor saw, alpha_b * b (exposure). alpha_b is drawn independently
    of the scene, so an output held to b must guess a gain the image does not carry, and that guess dominates
    the L1 gradient wherever the image has no laser to remove; held to alpha_b * b, G2 learns only the
    restoration, and the level head (applied to every image, lasered or not) brings the output to the scene's
    level (docs/models.md Sec. 13).
    """

    name: str | None = None
    variant: str = "sgan_b"
    size: str = "cpu"
    stem_width: int | None = None
    widths: tuple | None = None
    d_widths: tuple | None = None
    fe_features: int = 16
    fe_kernel: int = 5
    attention: bool = True
    key_channels: int = 8
    gamma_init: float = 1e-2
    g2_head_layers: int = 2
    coarse_to_fine: bool = True
    g1_residual: bool = True
    g2_linear_skip: bool = True
    g2_residual: bool = False
    g1_base: str = "sensor"
    g2_base: str = "i_b"
    g2_base_nsr: float = 3e-2
    g2_base_pad: str = "filled"
    laser_gate: bool = False
    laser_gate_f0: float = 1e-3
    g2_base_nsr_lasered: float = 3e-2
    g2_gate: bool = False
    g2_base_nsr_tuned: bool = False
    g1_halo: bool = False
    level_head: bool = False
    target_level: str = "scene"
    prefix: str = field(default="model", compare=False, repr=False)

    def __post_init__(self) -> None:
        p = self.prefix
        require_choice(f"{p}.variant", self.variant, VARIANTS)
        object.__setattr__(self, "name", network_name(f"{p}.name", self.name, self.variant))
        require_choice(f"{p}.size", self.size, tuple(SIZES))
        preset = SIZES[self.size]
        stem = preset["stem_width"] if self.stem_width is None else self.stem_width
        object.__setattr__(self, "stem_width", require_number(f"{p}.stem_width", stem, lo=1, hi=4096,
                                                              integer=True))
        # only null means "the preset's": an empty list is refused rather than silently replaced
        for key, n_min in (("widths", 1), ("d_widths", 2)):
            value = preset[key] if getattr(self, key) is None else getattr(self, key)
            object.__setattr__(self, key, _widths(f"{p}.{key}", value, n_min))
        require_number(f"{p}.fe_features", self.fe_features, lo=1, hi=1024, integer=True)
        require_number(f"{p}.fe_kernel", self.fe_kernel, lo=1, hi=15, integer=True)
        if self.fe_kernel % 2 == 0:
            raise ConfigError(f"{p}.fe_kernel", self.fe_kernel, "must be odd (same-size convolution)")
        require_number(f"{p}.key_channels", self.key_channels, lo=1, hi=1024, integer=True)
        require_number(f"{p}.gamma_init", self.gamma_init, lo=1e-7, hi=1e6)
        require_choice(f"{p}.g1_base", self.g1_base, G1_BASES)
        require_choice(f"{p}.g2_base", self.g2_base, G2_BASES)
        require_choice(f"{p}.g2_base_pad", self.g2_base_pad, G2_BASE_PADS)
        require_choice(f"{p}.target_level", self.target_level, TARGET_LEVELS)
        require_number(f"{p}.g2_base_nsr", self.g2_base_nsr, lo=1e-8, hi=1e4)
        if self.g2_base != "i_b" and not self.g2_residual:
            raise ConfigError(f"{p}.g2_base", self.g2_base, "needs model.g2_residual=true (it is what G2's residual "
                              "corrects)")
        require_number(f"{p}.laser_gate_f0", self.laser_gate_f0, lo=1e-8, hi=1.0)
        require_number(f"{p}.g2_base_nsr_lasered", self.g2_base_nsr_lasered, lo=1e-8, hi=1e4)
        if self.g2_gate and not (self.laser_gate and self.g2_residual):
            raise ConfigError(f"{p}.g2_gate", self.g2_gate, "needs model.laser_gate=true and model.g2_residual=true "
                              "(it scales G2's correction by the laser's presence)")
        if self.laser_gate and not self.g1_residual:
            raise ConfigError(f"{p}.laser_gate", self.laser_gate, "needs model.g1_residual=true (it scales G1's "
                              "correction)")
        require_number(f"{p}.g2_head_layers", self.g2_head_layers, lo=1, hi=8, integer=True)
        for key in ("attention", "coarse_to_fine", "g1_residual", "g2_linear_skip", "g2_residual", "laser_gate",
                    "g2_gate", "g2_base_nsr_tuned", "g1_halo", "level_head"):
            if not isinstance(getattr(self, key), bool):
                raise ConfigError(f"{p}.{key}", getattr(self, key), "must be true or false")
        if self.g2_base_nsr_tuned and self.g2_base != "wiener":
            raise ConfigError(f"{p}.g2_base_nsr_tuned", True, "needs model.g2_base=wiener (it tunes that Wiener "
                              "base's nsr)")

    @property
    def generator_block(self) -> str:
        """The UNets' residual block: "rft" (ResFFTBlock) for sgan_f, else "res" (ResBlock)."""
        return "rft" if self.variant == "sgan_f" else "res"

    @property
    def critic_block(self) -> str:
        """The critics' downsampling block: "ftc" (FFTConvBlock) for sgan_f, else "conv" (Conv-IN-LeakyReLU)."""
        return "ftc" if self.variant == "sgan_f" else "conv"

    @property
    def depth(self) -> int:
        """Number of UNet levels (len(widths)): the input side must be at least 2^depth."""
        return len(self.widths)

    def check_input_size(self, padded_size: int, key: str = "data.padded_size") -> None:
        """The coarse G2 scale (padded / 2) must survive the generator's encoder and the critics' patches: an
        L-level PatchGAN outputs floor(c / 2^(L-1)) - 2 values, so c >= 3 * 2^(L-1); a depth-d UNet needs c >= 2^d."""
        if padded_size % 2:
            raise ConfigError(key, padded_size, "must be even (G2's coarse scale is half of it)")
        coarse = padded_size // 2
        need = max(3 * 2 ** (len(self.d_widths) - 1), 2 ** self.depth)
        if coarse < need:
            raise ConfigError(key, padded_size, f"too small for model.size={self.size} ({self.depth} generator "
                              f"levels, {len(self.d_widths)} critic levels): the coarse scale ({coarse} px) must "
                              f"be >= {need} px, i.e. padded_size >= {2 * need}")
