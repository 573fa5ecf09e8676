"""codesign: end-to-end differentiable co-design of anti-dazzle phase masks and restoration networks."""
import importlib

from codesign.config import resolvers as _resolvers

__version__ = "0.1.0"
_resolvers.register()

# The modules that define specs register their config nodes when imported (codesign/config/store.py: every default
# has one source, its spec dataclass), so that any Hydra composition that imports codesign sees them. Mask-family
# and restorer plug-ins register themselves when codesign.optics.masks and codesign.models discover them.
_SPEC_MODULES = ("config.runtime", "optics.spec", "optics.masks", "sensor.spec", "data.scenes", "data.simulate_spec",
                 "models", "design.merit", "design.search_spec", "fab.surface", "fab.tolerance", "train.lsr_constraint",
                 "train.spec", "train.evaluation")
for _name in _SPEC_MODULES:
    importlib.import_module(f"codesign.{_name}")
importlib.import_module("codesign.models").restorer_kinds()

# The Python API (codesign/api.py, docs/api.md): ``from codesign import compose, psf_and_lsr, ...``, loaded on first
# use so that ``import codesign`` stays as cheap as the config registration above.
API = ("compose", "build_camera", "optical_system", "build_mask", "configured_mask", "published_mask",
       "psf_and_lsr", "scene_names", "sensor_image", "run", "checkpoint_config", "restore", "restore_image", "quality",
       "mask_search", "train_restorer", "OpticsSpec", "OpticalSystem", "Camera", "Mask", "ConfigError", "alpha_tag")


def __getattr__(name: str):
    if name in API:
        return getattr(importlib.import_module("codesign.api"), name)
    raise AttributeError(f"module 'codesign' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(API))


__all__ = list(API)
