"""Hand-written VGG16/VGG19 feature extractors in torchvision's ``features.N`` layout, loaded only from a user file.

torchvision is not a dependency and nothing is downloaded: the weights come from a file the user points to (a
plain state dict as saved by ``torch.save(torchvision.models.vgg19(weights=...).state_dict(), path)``). The module
indices equal torchvision's, so ``features.N.weight`` of such a file lands on ``self[N]``; ``classifier.*`` keys
are ignored. Every problem with the file raises :class:`ConfigError` naming the config key, the path and the first
offending tensor.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Sequence

import torch
import torch.nn as nn

from codesign.errors import ConfigError

_CONVS_PER_BLOCK = {"vgg16": (2, 2, 3, 3, 3), "vgg19": (2, 2, 4, 4, 4)}
_WIDTHS = (64, 128, 256, 512, 512)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _check_kind(kind: str) -> str:
    if kind not in _CONVS_PER_BLOCK:
        raise ConfigError("vgg kind", kind, f"must be one of {', '.join(_CONVS_PER_BLOCK)}")
    return kind


def layer_names(kind: str) -> list[str]:
    """Name of every module of ``features`` in index order: conv1_1, relu1_1, ..., pool1, conv2_1, ..."""
    names = []
    for b, n in enumerate(_CONVS_PER_BLOCK[_check_kind(kind)], 1):
        for i in range(1, n + 1):
            names += [f"conv{b}_{i}", f"relu{b}_{i}"]
        names.append(f"pool{b}")
    return names


def layer_index(kind: str, layer: int | str) -> int:
    """torchvision index of a layer given as that index or as a name such as ``"relu3_4"``."""
    names = layer_names(kind)
    if isinstance(layer, int) and not isinstance(layer, bool) and 0 <= layer < len(names):
        return layer
    if isinstance(layer, str) and layer in names:
        return names.index(layer)
    raise ConfigError(f"{kind} layer", layer, f"must be an index 0..{len(names) - 1} or a name such as "
                      f"{', '.join(n for n in names if n.startswith('relu'))}")


def _features(kind: str) -> nn.Sequential:
    layers: list[nn.Module] = []
    c_in = 3
    for n, width in zip(_CONVS_PER_BLOCK[_check_kind(kind)], _WIDTHS):
        for _ in range(n):
            # Not in-place (torchvision uses inplace=True): a tapped activation must not be overwritten by the
            # next layer; the state dict is identical either way.
            layers += [nn.Conv2d(c_in, width, 3, padding=1), nn.ReLU()]
            c_in = width
        layers.append(nn.MaxPool2d(2, 2))
    return nn.Sequential(*layers)


def vgg16_features() -> nn.Sequential:
    """VGG16 ``features`` (31 modules, convs at 0,2,5,7,10,12,14,17,19,21,24,26,28), randomly initialized."""
    return _features("vgg16")


def vgg19_features() -> nn.Sequential:
    """VGG19 ``features`` (37 modules, convs at 0,2,5,7,10,12,14,16,19,21,23,25,28,30,32,34), randomly
    initialized."""
    return _features("vgg19")


def freeze(module: nn.Module) -> nn.Module:
    """No gradients for the parameters, eval mode; returns the module."""
    module.requires_grad_(False)
    return module.eval()


def read_state_dict(path, key: str) -> dict[str, torch.Tensor]:
    """Load a plain state dict (tensors by name) from ``path`` onto the CPU, or raise ConfigError(key, path, ...).

    ``weights_only=True``: a pickled whole model (``torch.save(model)``) is refused; save ``model.state_dict()``.
    """
    if path is None or str(path) == "":
        raise ConfigError(key, path, "a weights file path is required")
    p = Path(str(path)).expanduser()
    if not p.is_file():
        raise ConfigError(key, str(path), f"file not found ({p.resolve()})")
    try:
        sd = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # unpickling errors come in many types; the message is what matters
        raise ConfigError(key, str(path), f"cannot be read as a torch state dict file: {type(e).__name__}: "
                          f"{str(e).splitlines()[0] if str(e) else ''}") from e
    if not isinstance(sd, Mapping) or not all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                              for k, v in sd.items()):
        raise ConfigError(key, str(path), f"is not a state dict (a mapping of names to tensors) but a "
                          f"{type(sd).__name__}; save model.state_dict()")
    return dict(sd)


def require_tensor(sd: Mapping[str, torch.Tensor], name: str, shape: Sequence[int], path, key: str,
                   what: str) -> torch.Tensor:
    """``sd[name]`` if present with ``shape``, else ConfigError naming the tensor and the expected shape."""
    shape = tuple(shape)
    if name not in sd:
        raise ConfigError(key, str(path), f"missing tensor {name!r} (expected shape {shape}); the file must hold "
                          f"{what}")
    if tuple(sd[name].shape) != shape:
        raise ConfigError(key, str(path), f"tensor {name!r} has shape {tuple(sd[name].shape)}, expected {shape}; "
                          f"the file must hold {what}")
    return sd[name]


def vgg_from_state_dict(kind: str, sd: Mapping[str, torch.Tensor], path, key: str,
                        prefix: str = "features.") -> nn.Sequential:
    """Build ``kind`` features and fill them from ``sd[prefix + N.weight/bias]``; frozen, eval mode.

    Keys outside ``prefix`` (``classifier.*``, LPIPS/DISTS heads) are ignored; a key under ``prefix`` that the
    architecture does not have (e.g. a batch-norm VGG or the other depth) is an error.
    """
    with torch.device("meta"):  # shapes only: skips the random init of ~20M parameters that would be overwritten
        model = _features(kind)
    what = f"a torchvision-layout {kind} state dict ({prefix}N.weight / {prefix}N.bias)"
    own = model.state_dict()
    values = {k: require_tensor(sd, prefix + k, v.shape, path, key, what).float().contiguous()
              for k, v in own.items()}
    extra = sorted(k for k in sd if k.startswith(prefix) and k[len(prefix):] not in own)
    if extra:
        raise ConfigError(key, str(path), f"unexpected tensor {extra[0]!r} for {kind}; the file must hold {what}")
    model.load_state_dict(values, assign=True)
    return freeze(model)


def load_vgg_features(kind: str, path, prefix: str = "features.",
                      key: str = "model.loss.vgg_weights") -> nn.Sequential:
    """VGG ``features`` ("vgg16" or "vgg19") from a torchvision-layout state dict file; frozen, eval mode.

    ``key`` is the config key named in errors (missing file, not a state dict, missing key, wrong shape).
    """
    _check_kind(kind)
    return vgg_from_state_dict(kind, read_state_dict(path, key), path, key, prefix)


def extract(features: nn.Sequential, x: torch.Tensor, indices: Sequence[int]) -> list[torch.Tensor]:
    """Outputs of ``features[i]`` for each i in ``indices`` (in that order); runs only up to the deepest one."""
    wanted = set(indices)
    out: dict[int, torch.Tensor] = {}
    for i, layer in enumerate(features):
        if i > max(wanted):
            break
        x = layer(x)
        if i in wanted:
            out[i] = x
    return [out[i] for i in indices]


class ImageNetInput(nn.Module):
    """(B,1,H,W) grayscale (or (B,3,H,W) RGB) in [0,1] -> (B,3,H,W) normalized by the ImageNet mean and std."""

    def __init__(self):
        super().__init__()
        # Not persistent: constants, not weights; keeps them out of checkpoints of modules that hold this one.
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B,3,H,W) ImageNet-normalized ``x``, grayscale replicated to 3 channels; ValueError for another shape."""
        if x.ndim != 4 or x.shape[1] not in (1, 3):
            raise ValueError(f"expected a (B,1,H,W) or (B,3,H,W) image, got shape {tuple(x.shape)}")
        x = x.expand(-1, 3, -1, -1) if x.shape[1] == 1 else x
        return (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)
