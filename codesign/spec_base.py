"""Shared behaviour of the frozen, validated parameter dataclasses (OpticsSpec, SensorSpec)."""
from __future__ import annotations

from dataclasses import fields
from typing import Any, Mapping

from codesign.errors import unknown_keys


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
        unknown_keys(prefix, cfg, {f.name for f in fields(cls)} - {"prefix"})
        return cls(**dict(cfg), prefix=prefix)
