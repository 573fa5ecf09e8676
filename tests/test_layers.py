"""The configuration is read at the boundary: only the experiments (codesign/experiments), the config plumbing
(codesign/config), the Python API and the entry point take the composed DictConfig; the library packages take
specs (frozen dataclasses, codesign/spec_base.py) or objects. Typed constructors are the exception by nature: a
``from_config`` / ``from_record`` method (a spec, model or mask family built from its node) and a ``build_*``
factory whose job is exactly "config -> object" (build_model, build_camera, build_mask, ...)."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent / "codesign"
# The boundary: these read the DictConfig by design.
BOUNDARY_DIRS = ("experiments", "config")
BOUNDARY_FILES = ("api.py", "__main__.py")
CONSTRUCTORS = ("from_config", "from_record")
# What still reads the config outside the boundary, with why; keep it short, and shrink it.
ALLOWED: dict[str, set[str]] = {}


def _reads_config(arg: ast.arg) -> bool:
    """A parameter that carries a config: named cfg or *_cfg, or annotated DictConfig."""
    named = arg.arg == "cfg" or arg.arg.endswith("_cfg")
    return named or (arg.annotation is not None and "DictConfig" in ast.unparse(arg.annotation))


def _offenders(path: Path) -> list[str]:
    """'path:line name' of every function of ``path`` that takes a config and is no typed constructor."""
    rel = path.relative_to(ROOT).as_posix()
    tree = ast.parse(path.read_text())
    parent = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    out = []
    for node in ast.walk(tree):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        method = isinstance(parent.get(node), ast.ClassDef)
        if (method and node.name in CONSTRUCTORS) or node.name.startswith("build_"):
            continue
        a = node.args
        if any(_reads_config(arg) for arg in a.posonlyargs + a.args + a.kwonlyargs):
            out.append(f"{rel}:{node.lineno} {node.name}")
    return out


def _library_files() -> list[Path]:
    files = []
    for p in sorted(ROOT.rglob("*.py")):
        rel = p.relative_to(ROOT)
        if rel.parts[0] in BOUNDARY_DIRS or rel.as_posix() in BOUNDARY_FILES:
            continue
        files.append(p)
    return files


def _found() -> list[str]:
    """Every offender of the library, 'path:line name' (about 0.3 s: parsed once for both tests)."""
    if not _FOUND:
        _FOUND.extend(o for p in _library_files() for o in _offenders(p))
    return _FOUND


_FOUND: list[str] = []


def test_library_functions_take_specs_not_the_config():
    left = [o for o in _found() if o.split()[1] not in ALLOWED.get(o.split(":")[0], ())]
    assert not left, ("library functions that take the config (cfg / *_cfg / DictConfig): build what they need "
                      "in the experiment, or give them a spec's from_config:\n" + "\n".join(left))


def test_the_allow_list_names_only_what_still_reads_the_config():
    found = {(o.split(":")[0], o.split()[1]) for o in _found()}
    stale = [(f, n) for f, names in ALLOWED.items() for n in names if (f, n) not in found]
    assert not stale, f"allowed but no longer reading the config (remove from ALLOWED): {stale}"
