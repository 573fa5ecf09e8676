"""The sandwich GAN (SGAN-B/E/F) and its parts; see docs/models.md."""
from codesign.models.sgan import SGAN, coordinates, downsample2, parameter_count, pyramid
from codesign.models.spec import SIZES, VARIANTS, ModelSpec
from codesign.models.wiener import classical_wiener, otf_from_kernel, wiener_filter


def build_sgan(cfg) -> SGAN:
    """SGAN from a model config mapping (the ``loss`` block, if present, is the trainer's and is ignored)."""
    values = {k: v for k, v in dict(cfg).items() if k != "loss"}
    return SGAN(ModelSpec.from_config(values))


__all__ = ["SGAN", "ModelSpec", "SIZES", "VARIANTS", "build_sgan", "classical_wiener", "coordinates",
           "downsample2", "otf_from_kernel", "parameter_count", "pyramid", "wiener_filter"]
