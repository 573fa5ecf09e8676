"""Every public function of codesign/ has a docstring (issue 58): module-level functions and the methods of public
classes whose names do not start with ``_`` (nested functions are implementation details and are not scanned)."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent / "codesign"
FUNCTIONS = (ast.FunctionDef, ast.AsyncFunctionDef)


def _missing(path: Path) -> list[str]:
    """``path:line name`` of each public function or method of a public class in ``path`` without a docstring."""
    tree, out = ast.parse(path.read_text()), []
    for node in tree.body:
        members = [(node, "")] if isinstance(node, FUNCTIONS) else []
        if isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            members = [(m, node.name + ".") for m in node.body if isinstance(m, FUNCTIONS)]
        out += [f"{path.relative_to(ROOT.parent)}:{f.lineno} {owner}{f.name}" for f, owner in members
                if not f.name.startswith("_") and ast.get_docstring(f) is None]
    return out


def test_public_functions_have_docstrings():
    missing = [line for path in sorted(ROOT.rglob("*.py")) for line in _missing(path)]
    assert not missing, "public functions without a docstring:\n" + "\n".join(missing)
