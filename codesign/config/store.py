"""The single source of every config default: each spec dataclass's field defaults, registered as a Hydra config
node (ConfigStore) by the package that defines the spec, on import. conf/ then holds only what overrides them:
variants, presets and experiments. ``python -m codesign +experiment=NAME --cfg job`` prints the composed result.
"""
from __future__ import annotations

from dataclasses import MISSING, fields, is_dataclass
from typing import Any

from hydra.core.config_store import ConfigStore

# (group, option) -> the spec dataclasses whose defaults the option registers (the first: its keys; the others:
# nested nodes, e.g. model.loss), what the config reference documents (codesign/config/reference.py,
# docs/config.md); _made: the specs of the spec_node calls since the last register, which register takes
SPECS: dict[tuple[str, str], tuple[type, ...]] = {}
# group -> the spec dataclass of a group whose options are YAML files in conf/ (e.g. material), for the reference
YAML_GROUPS: dict[str, type] = {}
_made: list[type] = []


def _plain(value: Any) -> Any:
    if is_dataclass(value):
        return _node(type(value))
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    return value


def spec_node(cls, drop: tuple[str, ...] = (), **overrides: Any) -> dict:
    """The config node of a spec dataclass: every field but ``prefix`` and ``drop`` with its default (tuples as
    lists, nested specs as nodes), then ``overrides``."""
    out = _node(cls, drop)
    out.update(overrides)
    _made.append(cls)
    return out


def _node(cls, drop: tuple[str, ...] = ()) -> dict:
    out = {}
    for f in fields(cls):
        if f.name == "prefix" or f.name in drop:
            continue
        out[f.name] = _plain(f.default_factory() if f.default_factory is not MISSING else f.default)
    return out


def register(group: str, name: str, node: dict, package: str | None = None, spec: type | None = None) -> None:
    """Make ``node`` the config option ``group=name`` (e.g. optics=default); ``package``: where it lands
    (default: at the group's key; _global_: at the root); ``spec``: the dataclass that documents its keys (default:
    the one whose spec_node made ``node``)."""
    made = ((spec,) if spec else ()) + tuple(c for c in _made if c is not spec)
    _made.clear()
    if made:
        SPECS[(group, name)] = made
    ConfigStore.instance().store(group=group, name=name, node=node, package=package)


def document(group: str, spec: type) -> None:
    """Name ``spec`` as the dataclass whose fields are the keys of config group ``group``, whose options are YAML
    files in conf/GROUP/ rather than registered nodes (e.g. material): for the config reference, docs/config.md."""
    YAML_GROUPS[group] = spec
