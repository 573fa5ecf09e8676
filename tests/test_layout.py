"""The package layout is the data flow: each package imports only the packages before it, only the entry point
imports the experiments (codesign.experiments), there are no import cycles, and no module uses another's private
names."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent / "codesign"
# The packages in data-flow order (README.md's Layout): a package may import itself and those listed before it.
# "core" is codesign/errors.py, codesign/spec_base.py and codesign/signals.py (stopping any experiment cleanly).
ORDER = ("core", "config", "io", "data", "optics", "sensor", "camera", "models", "design", "fab", "train",
         "experiments")
ENTRY = "codesign.__main__"
# The Python API sits above every package like the entry point: it may run the experiments, nothing imports it
# (its argument checks, codesign/api_checks.py, sit with it).
ENTRIES = (ENTRY, "codesign.api", "codesign.api_checks")


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _package(module: str) -> str:
    parts = module.split(".")
    if len(parts) == 1 or module in ENTRIES:
        return "root"  # codesign/__init__.py (registers the config nodes), the entry point and the Python API
    return "core" if parts[1] in ("errors", "spec_base", "signals") else parts[1]


MODULES = {_module_name(p): p for p in sorted(ROOT.rglob("*.py"))}


def _imports(path: Path) -> list[tuple[str, list[str], int]]:
    """(imported module, imported names, line) of every import statement of a file, at any depth."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(a.name, [], node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.module, [a.name for a in node.names], node.lineno))
    return out


def _targets(module: str, names: list[str]) -> list[str]:
    """The codesign modules an import reaches (``from codesign.x import y`` reaches codesign.x.y when y is a
    module, else codesign.x)."""
    if not module.startswith("codesign"):
        return []
    subs = [f"{module}.{n}" for n in names if f"{module}.{n}" in MODULES]
    return subs or [module]


EDGES = {m: sorted({t for mod, names, _ in _imports(p) for t in _targets(mod, names)}) for m, p in MODULES.items()}


def test_the_packages_are_the_ones_of_the_layout():
    found = {_package(m) for m in MODULES} - {"root"}
    assert found == set(ORDER), sorted(found ^ set(ORDER))


@pytest.mark.parametrize("module", sorted(m for m in MODULES if _package(m) not in ("root",)))
def test_a_package_imports_only_the_packages_before_it(module):
    mine = ORDER.index(_package(module))
    late = [t for t in EDGES[module] if _package(t) not in ("root",) and ORDER.index(_package(t)) > mine]
    assert not late, f"{module} ({_package(module)}) imports later packages: {late}"


def test_only_the_entry_point_imports_the_experiments():
    importers = sorted(m for m, targets in EDGES.items() if _package(m) != "experiments" and m not in ENTRIES
                       and any(_package(t) == "experiments" for t in targets))
    assert importers == []
    # and one experiment module never imports another (their shared runner is codesign.experiments itself)
    from codesign.experiments import _SUPPORT

    experiments = [m for m in MODULES if m.startswith("codesign.experiments.")
                   and m.rsplit(".", 1)[1] not in _SUPPORT]
    for m in experiments:
        assert not [t for t in EDGES[m] if t in experiments and t != m], m


def test_no_import_cycles():
    state: dict[str, int] = {}
    cycle: list[str] = []

    def visit(m: str, stack: list[str]) -> bool:
        state[m] = 1
        for t in EDGES.get(m, []):
            if t not in MODULES or t == m or t.startswith(m + "."):  # a package importing its own submodules
                continue
            if m.startswith(t + "."):  # a submodule importing its package's __init__ re-exports: not a cycle
                continue
            if state.get(t) == 1:
                cycle.extend(stack[stack.index(t):] + [t] if t in stack else [m, t])
                return True
            if state.get(t) is None and visit(t, stack + [t]):
                return True
        state[m] = 2
        return False

    for m in MODULES:
        if state.get(m) is None and visit(m, [m]):
            break
    assert not cycle, " -> ".join(cycle)


def _private_uses(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    aliases = {}  # local name -> codesign module it stands for
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("codesign"):
                    aliases[a.asname or a.name.split(".")[0]] = a.name
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("codesign"):
            for a in node.names:
                if a.name.startswith("_") and not a.name.startswith("__"):
                    found.append(f"line {node.lineno}: from {node.module} import {a.name}")
                if f"{node.module}.{a.name}" in MODULES:
                    aliases[a.asname or a.name] = f"{node.module}.{a.name}"
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases \
                and node.attr.startswith("_") and not node.attr.startswith("__"):
            found.append(f"line {node.lineno}: {node.value.id}.{node.attr}")
    return found


def test_no_module_uses_another_modules_private_names():
    found = {m: uses for m, p in MODULES.items() if (uses := _private_uses(p))}
    assert not found, found


def test_nothing_in_the_library_imports_the_python_api():
    """codesign/api.py sits above every package (it runs the experiments): no module imports it; codesign/__init__.py
    loads it on first use of one of its names (importlib, not an import statement)."""
    assert "codesign.api" in MODULES
    importers = sorted(m for m, targets in EDGES.items() if {"codesign.api", "codesign.api_checks"} & set(targets)
                       and m not in ENTRIES[1:])
    assert importers == []
