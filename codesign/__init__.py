"""codesign: end-to-end differentiable co-design of anti-dazzle phase masks and restoration networks."""
__version__ = "0.1.0"
