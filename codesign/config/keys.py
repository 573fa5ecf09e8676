"""Config validation shared by the typed constructors (``from_config``): a key that no field reads."""
from __future__ import annotations

from typing import Any

from codesign.errors import ConfigError


def unknown_keys(prefix: str, cfg: Any, known) -> None:
    """ConfigError naming the first key of mapping ``cfg`` that is not in ``known`` (a typo would otherwise be
    ignored silently and the default used)."""
    extra = sorted(set(cfg) - set(known)) if hasattr(cfg, "keys") else []
    if extra:
        raise ConfigError(f"{prefix}.{extra[0]}", cfg[extra[0]], f"unknown key; allowed: {', '.join(sorted(known))}")
