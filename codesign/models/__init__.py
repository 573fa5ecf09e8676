"""Restoration networks behind one interface (codesign/models/restorer.py): the sandwich GAN (SGAN-B/E/F) and
plug-ins; their blocks, losses and the quality metrics; see docs/models.md."""
from codesign.models.restorer import (
    Restorer,
    TrainContext,
    build_restorer,
    parameter_count,
    restorer_kinds,
)
from codesign.models.sandwich import coordinates, downsample2, pyramid
from codesign.models.sgan import SGAN
from codesign.models.spec import SIZES, VARIANTS, ModelSpec
from codesign.models.wiener import classical_wiener, wiener_filter
from codesign.sensor.kernels import otf_from_kernel


def build_sgan(cfg) -> SGAN:
    """SGAN from a model config mapping (architecture keys and the ``loss`` block)."""
    return SGAN.from_config({k: v for k, v in dict(cfg).items() if k != "kind"})


__all__ = ["Restorer", "TrainContext", "SGAN", "ModelSpec", "SIZES", "VARIANTS", "build_restorer", "build_sgan",
           "classical_wiener", "coordinates", "downsample2", "otf_from_kernel", "parameter_count", "pyramid",
           "restorer_kinds", "wiener_filter"]
