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
