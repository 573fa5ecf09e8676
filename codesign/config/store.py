"""The single source of every config default: each spec dataclass's field defaults, registered as a Hydra config
node (ConfigStore) by the package that defines the spec, on import. conf/ then holds only what overrides them:
variants, presets and experiments. ``python -m codesign +experiment=NAME --cfg job`` prints the composed result.
"""
from __future__ import annotations

from dataclasses import MISSING, fields, is_dataclass
from typing import Any

from hydra.core.config_store import ConfigStore


def _plain(value: Any) -> Any:
    if is_dataclass(value):
        return spec_node(type(value))
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    return value


def spec_node(cls, drop: tuple[str, ...] = (), **overrides: Any) -> dict:
    """The config node of a spec dataclass: every field but ``prefix`` and ``drop`` with its default (tuples as
    lists, nested specs as nodes), then ``overrides``."""
    out = {}
    for f in fields(cls):
        if f.name == "prefix" or f.name in drop:
            continue
        out[f.name] = _plain(f.default_factory() if f.default_factory is not MISSING else f.default)
    out.update(overrides)
    return out


def register(group: str, name: str, node: dict, package: str | None = None) -> None:
    """Make ``node`` the config option ``group=name`` (e.g. optics=default); ``package``: where it lands
    (default: at the group's key; _global_: at the root)."""
    ConfigStore.instance().store(group=group, name=name, node=node, package=package)
