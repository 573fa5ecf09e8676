"""From a design to a fabricated plate and back: the wrapped phase as a surface-height map in a material
(materials), quantized and resampled onto a fabrication grid (surface), and Monte Carlo over fabrication and
assembly errors (tolerance)."""
