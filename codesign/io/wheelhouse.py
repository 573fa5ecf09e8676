"""An offline wheelhouse for a GPU node that has no package registry.

On a connected machine where codesign is installed (``bash install.sh``), one command collects the wheels of what
codesign needs, at the versions installed here (the ones its tests passed with), for the node's Python and
platform:

    python -m codesign.io.wheelhouse wheelhouse/ [--python-version 3.12] [--have node-packages.txt] [--with-torch]

On the node, from the checkout (which it needs anyway for conf/, tests/ and benchmarks/), with no network:

    bash install.sh --wheelhouse wheelhouse/

torch is left out by default, with everything only torch needs (the CUDA libraries, triton, sympy, ...): a GPU
node's image brings a CUDA build of torch, and the wheelhouse stays a few MB instead of several GB.
``--have FILE`` (``python3 -m pip list --format=freeze`` run on the node, or one package name per line) leaves out
what the node already has. codesign itself is installed from the checkout (editable), not from a wheel: its Hydra
configs live in the checkout's conf/, beside the package.

Why not ``pip download`` of the whole closure for the node's platform: that makes pip resolve torch's CUDA build
(GB of metadata lookups), and it refuses packages published only as source (hydra-core's antlr4 runtime). Here the
closure comes from the installed distributions' metadata with the markers evaluated for the node; each package is
downloaded as the node's wheel, and a pure-Python package without one is built into a wheel here.
"""
from __future__ import annotations

import argparse
import importlib.metadata as md
import platform
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from packaging.markers import default_environment
from packaging.requirements import Requirement

from codesign.io.files import write_json

# The platforms a manylinux x86_64 node accepts (pip matches a manylinux_2_N tag exactly, so several are listed).
DEFAULT_PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64",
                     "manylinux2014_x86_64", "manylinux1_x86_64")
EXTRAS = ("dev",)  # pytest: the node runs the CUDA test subset
PYPROJECT = Path(__file__).resolve().parents[2] / "pyproject.toml"


def build_requirements() -> list[str]:
    """Names in pyproject.toml's [build-system] requires: pip's isolated build of the editable install takes them
    from the wheelhouse too (an isolated build never uses the node's own setuptools), so they are never left out."""
    try:
        import tomllib
    except ImportError:  # Python 3.10
        return ["setuptools"]
    reqs = tomllib.loads(PYPROJECT.read_text())["build-system"]["requires"]
    return sorted(canonical(Requirement(r).name) for r in reqs)


def canonical(name: str) -> str:
    """PEP 503 normalized name: lower case, runs of -_. as one -."""
    return re.sub(r"[-_.]+", "-", name).lower()


def target_environment(python_version: str) -> dict:
    """Marker environment of a Linux x86_64 CPython ``python_version`` (e.g. "3.12")."""
    env = dict(default_environment())
    env.update(python_version=python_version, python_full_version=f"{python_version}.0", sys_platform="linux",
               platform_system="Linux", platform_machine="x86_64", os_name="posix",
               implementation_name="cpython", platform_python_implementation="CPython")
    return env


def requirements_of(requires: list[str] | None, env: dict, extras: tuple[str, ...] = ()) -> list[Requirement]:
    """The requirements that apply in ``env`` (with ``extras`` asked for)."""
    out = []
    for text in requires or []:
        req = Requirement(text)
        if req.marker is None or any(req.marker.evaluate({**env, "extra": e}) for e in ("",) + tuple(extras)):
            out.append(req)
    return out


def closure(root: str, env: dict, extras: tuple[str, ...], requires=None) -> dict[str, list[str]]:
    """{package: [its dependencies]} of every distribution reachable from ``root``'s requirements in ``env``,
    read from the installed metadata (``requires(name) -> list[str] | None`` for tests). A requirement that is not
    installed here is an error: the wheelhouse holds what this machine runs, nothing it has not tested."""
    requires = requires or md.requires
    graph: dict[str, list[str]] = {}
    todo = [(canonical(root), extras)]
    while todo:
        name, ex = todo.pop()
        if name in graph:
            continue
        try:
            reqs = requirements_of(requires(name), env, ex)
        except md.PackageNotFoundError:
            raise SystemExit(f"wheelhouse: {name} is required but not installed here; run `bash install.sh` first "
                             "(the wheelhouse takes the versions installed on this machine)") from None
        graph[name] = sorted({canonical(r.name) for r in reqs})
        todo += [(canonical(r.name), tuple(sorted(r.extras))) for r in reqs]
    return graph


def select(graph: dict[str, list[str]], root: str, skip: set[str]) -> list[str]:
    """Packages reachable from ``root`` without passing through a name in ``skip`` (``root`` itself excluded):
    skipping torch drops what only torch needs (nvidia-*, triton) but keeps what others need too (numpy)."""
    seen, todo = set(), list(graph.get(root, []))
    while todo:
        name = todo.pop()
        if name in seen or name in skip:
            continue
        seen.add(name)
        todo += graph.get(name, [])
    return sorted(seen)


def read_have(path: Path) -> set[str]:
    """Names in a ``pip list --format=freeze`` / ``pip freeze`` / one-name-per-line file."""
    names = set()
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line and not line.startswith("-"):
            names.add(canonical(re.split(r"[=<>!~ @;\[]", line, maxsplit=1)[0]))
    return names


def is_pure(name: str) -> bool:
    """Whether the installed distribution is pure Python (a py3-none-any wheel builds anywhere)."""
    wheel = md.distribution(name).read_text("WHEEL") or ""
    tags = [line.split(":", 1)[1].strip() for line in wheel.splitlines() if line.startswith("Tag:")]
    return bool(tags) and all(t.endswith("-none-any") for t in tags)


def fetch(name: str, version: str, out: Path, python_version: str, platforms: tuple[str, ...]) -> str:
    """Put ``name==version``'s wheel for the node into ``out``; returns how ("downloaded" or "built here")."""
    spec = f"{name}=={version}"
    plat = [a for p in platforms for a in ("--platform", p)]
    cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:",
           "--python-version", python_version, "--implementation", "cp", *plat, "-d", str(out), spec]
    got = subprocess.run(cmd, capture_output=True, text=True)
    if got.returncode == 0:
        return "downloaded"
    if not is_pure(name):
        raise SystemExit(f"wheelhouse: no wheel of {spec} for CPython {python_version} on {', '.join(platforms)}:"
                         f"\n{got.stderr.strip()[-2000:]}")
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "-w", str(out), spec],
                           capture_output=True, text=True)
    if built.returncode != 0:
        raise SystemExit(f"wheelhouse: could not build a wheel of {spec}:\n{built.stderr.strip()[-2000:]}")
    return "built here"


def plan(python_version: str, have: set[str], with_torch: bool, root: str = "codesign") -> dict:
    """What goes in: {"packages": {name: version}, "left_out": {name: why}}."""
    graph = closure(root, target_environment(python_version), EXTRAS)
    skip = set() if with_torch else {"torch"}
    wanted = select(graph, canonical(root), skip)
    build = build_requirements()
    have = have - set(build)
    wanted = sorted(set(wanted) | set(build))
    left = {n: "the node has it (--have)" for n in wanted if n in have}
    if not with_torch:
        only_torch = sorted(set(select(graph, canonical(root), set())) - set(wanted))
        left.update({n: "torch and what only torch needs: the node's image brings its CUDA build "
                        "(--with-torch to include)" for n in only_torch})
    return {"packages": {n: md.version(n) for n in wanted if n not in have}, "left_out": left}


def build(out: Path, python_version: str, platforms: tuple[str, ...], have: set[str], with_torch: bool) -> dict:
    """Fetch every wheel of the plan (for ``python_version`` on ``platforms``, without the ``have`` packages, with
    torch when ``with_torch``) into ``out`` and write its wheelhouse.json; returns that manifest."""
    what = plan(python_version, have, with_torch)
    out.mkdir(parents=True, exist_ok=True)
    how = {}
    with tempfile.TemporaryDirectory(dir=out) as tmp:  # wheels land in out only when fetched whole
        for i, (name, version) in enumerate(what["packages"].items(), 1):
            print(f"[{i}/{len(what['packages'])}] {name}=={version}", flush=True)
            how[name] = fetch(name, version, Path(tmp), python_version, platforms)
        for f in Path(tmp).iterdir():
            f.replace(out / f.name)
    wheels = sorted(out.glob("*.whl"))
    manifest = {"python_version": python_version, "platforms": list(platforms), "built_on": platform.platform(),
                "packages": {n: {"version": v, "how": how[n]} for n, v in what["packages"].items()},
                "left_out": what["left_out"], "wheels": [w.name for w in wheels],
                "megabytes": round(sum(w.stat().st_size for w in wheels) / 2**20, 2)}
    write_json(out / "wheelhouse.json", manifest)
    return manifest


def main(argv=None) -> None:
    """``python -m codesign.io.wheelhouse OUT``: build the wheelhouse a GPU node without a registry installs from."""
    ap = argparse.ArgumentParser(prog="python -m codesign.io.wheelhouse", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path, help="folder for the wheels (created; earlier wheels in it are kept)")
    ap.add_argument("--python-version", default="3.12", help="the node's Python, MAJOR.MINOR (default 3.12)")
    ap.add_argument("--platform", action="append", default=None,
                    help=f"a wheel platform tag the node accepts (repeat; default: {', '.join(DEFAULT_PLATFORMS)})")
    ap.add_argument("--have", type=Path, default=None,
                    help="the node's `python3 -m pip list --format=freeze` (or one name per line): left out")
    ap.add_argument("--with-torch", action="store_true", help="include torch and what only torch needs")
    a = ap.parse_args(argv)
    if not re.fullmatch(r"3\.\d{1,2}", a.python_version):
        ap.error(f"--python-version {a.python_version!r}: must be MAJOR.MINOR, e.g. 3.12")
    if a.have is not None and not a.have.is_file():
        ap.error(f"--have {a.have}: no such file (make it on the node: python3 -m pip list --format=freeze > FILE)")
    if a.out.exists() and not a.out.is_dir():
        ap.error(f"{a.out}: exists and is not a folder")
    have = read_have(a.have) if a.have else set()
    m = build(a.out, a.python_version, tuple(a.platform or DEFAULT_PLATFORMS), have, a.with_torch)
    print(f"wheelhouse {a.out}: {len(m['wheels'])} wheels, {m['megabytes']:.1f} MB for CPython {a.python_version}; "
          f"left out {len(m['left_out'])} ({', '.join(sorted(m['left_out'])) or 'none'}). On the node: "
          f"bash install.sh --wheelhouse {a.out}")


if __name__ == "__main__":
    main()
