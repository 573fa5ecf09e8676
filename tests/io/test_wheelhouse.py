"""The offline wheelhouse: what goes in (markers for the node's Python, torch's closure left out, --have), and the
whole path: build on this machine, install with no index into a fresh environment, import codesign."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from codesign.io import wheelhouse as wh

REPO = Path(__file__).resolve().parents[2]


def test_markers_are_evaluated_for_the_node_and_extras_only_when_asked():
    reqs = ["numpy>=1.24", 'tomli; python_version < "3.11"', 'pytest>=7; extra == "dev"',
            'pywin32; sys_platform == "win32"', 'docs-only; extra == "docs"']
    env = wh.target_environment("3.12")
    assert [r.name for r in wh.requirements_of(reqs, env)] == ["numpy"]
    assert [r.name for r in wh.requirements_of(reqs, env, ("dev",))] == ["numpy", "pytest"]
    assert [r.name for r in wh.requirements_of(reqs, wh.target_environment("3.10"))] == ["numpy", "tomli"]


def test_torch_closure_is_left_out_but_what_others_share_with_it_stays():
    meta = {"codesign": ["torch>=2.3", "kornia>=0.7", "numpy"], "kornia": ["torch>=2.5", "kornia_rs"],
            "torch": ["numpy", "triton; platform_machine == 'x86_64'", "nvidia-cublas-cu12", "sympy"],
            "sympy": ["mpmath"], "mpmath": [], "numpy": [], "triton": [], "nvidia-cublas-cu12": [], "kornia-rs": []}
    graph = wh.closure("codesign", wh.target_environment("3.12"), (), requires=lambda n: meta[n])
    assert wh.select(graph, "codesign", {"torch"}) == ["kornia", "kornia-rs", "numpy"]
    assert wh.select(graph, "codesign", set()) == sorted(set(meta) - {"codesign"})


def test_a_requirement_not_installed_here_is_named():
    def requires(name):
        if name == "ghost":
            raise wh.md.PackageNotFoundError(name)
        return ["ghost>=1"]

    with pytest.raises(SystemExit, match="wheelhouse: ghost is required but not installed here; run "
                                         "`bash install.sh` first"):
        wh.closure("codesign", wh.target_environment("3.12"), (), requires=requires)


def test_have_file_reads_freeze_lines_and_bare_names(tmp_path):
    f = tmp_path / "node.txt"
    f.write_text("torch==2.11.0\nNumPy==2.5.2\n# comment\nscikit_image\n-e git+x#egg=y\npytest @ file:///x\n")
    assert wh.read_have(f) == {"torch", "numpy", "scikit-image", "pytest"}


def test_plan_of_this_installation_for_python_3_12():
    p = wh.plan("3.12", have={"kornia", "setuptools"}, with_torch=False)
    assert {"hydra-core", "nlopt", "omegaconf", "numpy", "scipy"} <= set(p["packages"])
    assert not {n for n in p["packages"] if n == "torch" or n.startswith("nvidia-") or n == "triton"}
    assert p["left_out"]["kornia"] == "the node has it (--have)"
    assert p["left_out"]["torch"].startswith("torch and what only torch needs")
    assert "setuptools" in p["packages"]  # the editable install's build backend: never left out
    assert "torch" in wh.plan("3.12", have=set(), with_torch=True)["packages"]


def test_install_sh_refuses_a_missing_folder_and_unknown_arguments(tmp_path):
    out = subprocess.run(["bash", str(REPO / "install.sh"), "--wheelhouse", str(tmp_path / "none")],
                         capture_output=True, text=True)
    assert out.returncode == 2 and f"--wheelhouse {tmp_path / 'none'}: no such folder" in out.stderr
    out = subprocess.run(["bash", str(REPO / "install.sh"), "--fast"], capture_output=True, text=True)
    assert out.returncode == 2 and "unknown argument '--fast'; allowed: --wheelhouse DIR" in out.stderr


def node_environment(venv: Path) -> Path:
    """A fresh venv that sees every package the running interpreter sees, wherever that interpreter lives: a system
    Python, a virtualenv (whose packages ``--system-site-packages`` alone would not show: the new venv's base is the
    base interpreter) or a conda-style prefix. Each of this interpreter's site directories is added to the new
    environment as a site directory (its .pth files processed too), after the environment's own."""
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    mine = [p for p in sys.path if Path(p).name in ("site-packages", "dist-packages") and Path(p).is_dir()]
    site_dir = subprocess.run([str(venv / "bin" / "python"), "-c", "import sysconfig; print(sysconfig.get_paths()"
                               "['purelib'])"], capture_output=True, text=True, check=True).stdout.strip()
    lines = "".join(f"import site; site.addsitedir({p!r})\n" for p in mine)
    (Path(site_dir) / "_codesign_test_parent_site.pth").write_text(lines)
    return venv


def test_the_node_environment_sees_what_this_interpreter_sees(tmp_path):
    venv = node_environment(tmp_path / "venv")
    out = subprocess.run([str(venv / "bin" / "python"), "-c", "import sys, torch, numpy, hydra; print(sys.prefix)"],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == str(venv)  # its own environment, where pip installs, not this one


@pytest.mark.slow  # 17 s: a venv install; twin: test_the_node_environment_sees_what_this_interpreter_sees
def test_build_then_install_with_no_index_into_a_fresh_environment(tmp_path):
    """This machine's Python as the node: everything installed here is 'had' by the node, so the wheelhouse holds
    the build backend only; the install then reaches no index (pip's own configuration switched off too)."""
    freeze = subprocess.run([sys.executable, "-m", "pip", "list", "--format=freeze"], capture_output=True,
                            text=True, check=True).stdout
    (tmp_path / "have.txt").write_text(freeze)
    version = f"{sys.version_info.major}.{sys.version_info.minor}"
    house = tmp_path / "house"
    built = subprocess.run([sys.executable, "-m", "codesign.io.wheelhouse", str(house), "--python-version", version,
                            "--have", str(tmp_path / "have.txt")], capture_output=True, text=True, cwd=REPO)
    said = (built.stderr + built.stdout).lower()
    if built.returncode != 0 and ("could not find a version" in said or "connection" in said):
        pytest.skip(f"no package registry reachable to build the wheelhouse: {built.stdout[-300:]}")
    assert built.returncode == 0, built.stderr[-2000:] + built.stdout[-2000:]
    assert [w.name.split("-")[0] for w in house.glob("*.whl")] == ["setuptools"]
    venv = node_environment(tmp_path / "venv")
    env = {**os.environ, "PYTHON": str(venv / "bin" / "python"), "PIP_CONFIG_FILE": os.devnull,
           "PIP_NO_INDEX": "1"}
    out = subprocess.run(["bash", str(REPO / "install.sh"), "--wheelhouse", str(house)], capture_output=True,
                         text=True, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip().splitlines()[-1].startswith("codesign 0.1.0, torch ")
    shown = subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "show", "codesign"], capture_output=True,
                           text=True, env=env).stdout
    assert "Editable project location: " + str(REPO) in shown
