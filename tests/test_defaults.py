"""One home per default: every default lives in its spec dataclass (registered as a Hydra node), the YAMLs in conf/
only override it, and no function in codesign/ writes a spec's default again as a parameter default. Each test
names where a default is written twice."""
from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest
import yaml
from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

import codesign  # noqa: F401 (registers every spec node)
from codesign.experiments import EXPERIMENTS, protocol
from codesign.spec_base import SpecMixin

REPO = Path(__file__).resolve().parent.parent
CONF = REPO / "conf"
# the spec node each config group's keys default to (conf/config.yaml's choices)
GROUP_NODES = {"optics": "default", "mask": "halfring", "sensor": "default", "model": "sgan_b", "data": "default",
               "trainer": "default", "metrics": "default", "logging": "default", "evaluate": "default",
               "codesign": "default", "search": "default", "export": "default", "tolerance": "default",
               "simulate": "default", "init": "default"}
MISSING = object()


def _node(group: str, name: str) -> dict:
    entry = ConfigStore.instance().load(f"{group}/{name}.yaml")
    return OmegaConf.to_container(entry.node, resolve=False)


def registered_default(path: str):
    """The registered default of a dotted key (MISSING when no spec holds it)."""
    group, _, rest = path.partition(".")
    if group not in GROUP_NODES or not rest:
        return MISSING
    node = _node(group, GROUP_NODES[group])
    for part in rest.split("."):
        if not isinstance(node, dict) or part not in node:
            return MISSING
        node = node[part]
    return node


def _leaves(data, prefix: str = "") -> dict:
    if isinstance(data, dict):
        out = {}
        for k, v in data.items():
            if k != "defaults":
                out.update(_leaves(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: data}


def _same(a, b) -> bool:
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return float(a) == float(b)
    return a == b


def yaml_settings() -> list[tuple[str, str, object]]:
    """(file, dotted key, value) of every value the YAMLs in conf/ set over a spec group (absolute paths)."""
    out = []
    for path in sorted(CONF.rglob("*.yaml")):
        rel = path.relative_to(CONF)
        if rel.parts[0] in ("hydra", "material"):
            continue
        text = path.read_text()
        data = yaml.safe_load(text) or {}
        if rel.parts[0] == "debug":  # the shrink: dotted keys under debug.overrides
            leaves = dict((data.get("debug") or {}).get("overrides") or {})
        else:
            glob = text.startswith("# @package _global_")
            leaves = _leaves(data, "" if glob else f"{rel.parts[0]}.")
        out += [(str(rel), k, v) for k, v in leaves.items()]
    return out


def yaml_duplicates(settings: list[tuple[str, str, object]]) -> list[str]:
    """The settings that write a registered default again; the debug shrink may set a default back where a group
    option changes it (optics=paper's propagator)."""
    undone = {k for f, k, v in settings if not f.startswith("debug/") and not _same(registered_default(k), v)}
    return [f"{f}: {k} = {v!r} is the default already ({k.split('.')[0]} spec)" for f, k, v in settings
            if (d := registered_default(k)) is not MISSING and _same(d, v)
            and not (f.startswith("debug/") and k in undone)]


def test_no_yaml_sets_a_key_to_its_registered_default():
    assert yaml_duplicates(yaml_settings()) == []


def test_no_experiment_shrinks_a_key_to_its_registered_default():
    twice = [f"{n}: smoke {k} = {v!r}" for n in EXPERIMENTS for k, v in protocol(n).smoke.items()
             if (d := registered_default(k)) is not MISSING and _same(d, v)]
    assert twice == []


def test_a_root_key_default_is_written_in_one_place():
    seen: dict[tuple, list[str]] = {}
    for path in sorted((CONF / "experiment").glob("*.yaml")):
        for k, v in (yaml.safe_load(path.read_text()) or {}).items():
            if k not in ("defaults", "task") and not isinstance(v, dict):
                seen.setdefault((k, repr(v)), []).append(path.name)
    assert {k: files for k, files in seen.items() if len(files) > 1} == {}


def _spec_defaults() -> dict[str, set]:
    """Field name -> {(default, spec)} of every spec dataclass's scalar and tuple defaults."""
    def subclasses(c):
        return {s for d in c.__subclasses__() for s in {d} | subclasses(d)}

    homes: dict[str, set] = {}
    for cls in subclasses(SpecMixin):
        for f in dataclasses.fields(cls) if dataclasses.is_dataclass(cls) else ():
            d = f.default
            if f.name != "prefix" and isinstance(d, (int, float, str, tuple)) and not isinstance(d, bool):
                homes.setdefault(f.name, set()).add((d, cls.__name__))
    return homes


# parameters named otherwise than the spec field whose default they would repeat
ALIASES = {"p": "lsr_p", "tolerance": "recheck_tolerance"}


def signature_duplicates(source: str, where: str, homes: dict) -> list[str]:
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        a = node.args
        pos = a.posonlyargs + a.args
        pairs = list(zip(pos[len(pos) - len(a.defaults):], a.defaults))
        pairs += [(arg, d) for arg, d in zip(a.kwonlyargs, a.kw_defaults) if d is not None]
        for arg, d in pairs:
            try:
                value = ast.literal_eval(d)
            except ValueError:  # a name: e.g. the spec's own attribute, the one home
                continue
            if value is None or isinstance(value, bool):
                continue
            name = ALIASES.get(arg.arg, arg.arg)
            for default, spec in homes.get(name, ()):
                if _same(default, value):
                    found.append(f"{where}:{node.lineno} {node.name}({arg.arg}={value!r}): the default of "
                                 f"{spec}.{name}")
    return found


def test_no_function_repeats_a_spec_default_as_its_parameter_default():
    homes = _spec_defaults()
    found = [hit for path in sorted((REPO / "codesign").rglob("*.py"))
             for hit in signature_duplicates(path.read_text(), str(path.relative_to(REPO)), homes)]
    assert found == []


@pytest.mark.parametrize("source,hits", [
    ("def f(x, p=16.0):\n    pass\n", 1),  # metrics.lsr_p under its usual short name
    ("def f(x, lsr_p=MetricsSpec.lsr_p):\n    pass\n", 0),  # the home itself
    ("def f(x, *, key_channels=8):\n    pass\n", 1),
    ("def f(x, key_channels):\n    pass\n", 0),
])
def test_the_signature_check_can_fail(source, hits):
    assert len(signature_duplicates(source, "x.py", _spec_defaults())) == hits


def test_the_yaml_check_can_fail():
    assert registered_default("metrics.lsr_p") == 16.0 and registered_default("nothing.here") is MISSING
    steps = registered_default("trainer.steps")
    assert yaml_duplicates([("trainer/x.yaml", "trainer.steps", steps)]) == [
        f"trainer/x.yaml: trainer.steps = {steps!r} is the default already (trainer spec)"]
    assert yaml_duplicates([("trainer/x.yaml", "trainer.steps", steps + 1)]) == []
