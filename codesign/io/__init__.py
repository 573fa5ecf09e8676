"""Small output helpers: atomic files (files), figures (plots), TensorBoard (tensorboard), 16-bit images (images)."""
