"""codesign: end-to-end differentiable co-design of anti-dazzle phase masks and restoration networks."""
from codesign.config import resolvers as _resolvers

__version__ = "0.1.0"
_resolvers.register()
