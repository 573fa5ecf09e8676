"""Shared behaviour of the frozen, validated parameter dataclasses (OpticsSpec, SensorSpec)."""
from __future__ import annotations

from dataclasses import fields
from typing import Any, Mapping

from codesign.errors import ConfigError


class SpecMixin:
    """``replace`` (re-validates) and ``from_config`` (rejects unknown keys, naming them) for a frozen dataclass
    whose last field is ``prefix``, the config path used in error messages."""

    def replace(self, **changes: Any):
        """A copy of the spec with ``changes`` (field name -> value), validated again."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values.update(changes)
        return type(self)(**values)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], prefix: str | None = None):
        """Build from a mapping (e.g. a Hydra config node); an unknown key is a ConfigError naming it."""
        prefix = prefix or cls.__dataclass_fields__["prefix"].default
        known = sorted({f.name for f in fields(cls)} - {"prefix"})
        # the key check of codesign.config.keys.unknown_keys, here because core (this module) is below config
        extra = sorted(set(cfg) - set(known)) if hasattr(cfg, "keys") else []
        if extra:
            raise ConfigError(f"{prefix}.{extra[0]}", cfg[extra[0]], f"unknown key; allowed: {', '.join(known)}")
        return cls(**dict(cfg), prefix=prefix)
