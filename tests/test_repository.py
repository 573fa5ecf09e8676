"""What the repository holds (issue 58): no committed file names a path of the machine it was written on, and the
top level holds the project's layout only (README.md's "Where to go next", docs/README.md's Layout)."""
from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# a temporary run folder, this checkout's absolute path, a user's home: written here so that it does not match itself
MACHINE_PATH = re.compile(r"/(?:tmp/[A-Za-z0-9_.-]+/|work/main|root/|home/)")
TOP_LEVEL = {".ci", ".gitignore", "LICENSE", "README.md", "pyproject.toml", "install.sh", "codesign", "conf", "tests",
             "docs", "benchmarks", "examples", "outputs", "data"}


def _tracked() -> list[str]:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout: nothing is tracked")
    out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    return [p for p in out.decode().split("\0") if p]


def machine_paths(path: Path) -> list[str]:
    """``path:line: text`` for every line of a text file that names a machine path; nothing for a binary file."""
    data = path.read_bytes()
    if b"\0" in data[:8192]:
        return []
    return [f"{path.relative_to(ROOT)}:{n}: {line.strip()[:160]}"
            for n, line in enumerate(data.decode("utf-8", errors="replace").splitlines(), 1)
            if MACHINE_PATH.search(line)]


def test_the_machine_path_pattern_finds_what_it_should(tmp_path):
    tmp = "/" + "tmp"
    cases = {f"checkpoint={tmp}/fc65/outputs/x.pt": True, f"cd /{'work'}/{'main'} && ls": True,
             f"/{'root'}/out/gpu": True, f"/{'home'}/user/data": True, "<tmp>/fc65/outputs/x.pt": False,
             "../shared/data/scenes": False, f"--out {tmp}/seeds": False, "benchmarks/results/gpu/gpu.json": False}
    assert {text: bool(MACHINE_PATH.search(text)) for text in cases} == cases


def _machine_paths_in(names: list[str]) -> str:
    found = [hit for name in names if (ROOT / name).is_file() and not (ROOT / name).is_symlink()
             for hit in machine_paths(ROOT / name)]
    shown = "\n".join(found[:40]) + (f"\n... and {len(found) - 40} more" if len(found) > 40 else "")
    return f"{len(found)} lines name a machine path (make them repository-relative or <tmp>/...):\n{shown}" \
        if found else ""


def test_no_committed_file_names_a_path_of_the_machine_it_was_written_on():
    """Results files, logs and pages record commands as they ran: the paths in them are relative to the repository,
    or placeholders (<tmp>/RUN/..., <out>/..., /path/to/...)."""
    problems = _machine_paths_in(_tracked())
    assert not problems, problems


def test_the_top_level_holds_the_layout_only():
    stray = sorted({name.split("/", 1)[0] for name in _tracked()} - TOP_LEVEL)
    assert not stray, f"tracked at the top level outside the layout: {stray}"
