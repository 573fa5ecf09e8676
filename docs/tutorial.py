"""Run every command of docs/tutorial.md, in order, exactly as printed there (the ```bash blocks), and collect the
pictures the page shows.

    python docs/tutorial.py                      # the commands as printed, from the repository root
    python docs/tutorial.py --smoke              # each with debug=smoke appended (seconds each; the tests do this)
    python docs/tutorial.py --smoke --root DIR --pictures DIR/pictures

--root: the folder the commands run in (their outputs/tutorial/... paths are relative to it); --pictures: where
the page's pictures are copied (docs/tutorial/ is where the page looks). A run stops at the first command that
fails, printing its output.
"""
from __future__ import annotations

import argparse
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PAGE = REPO / "docs" / "tutorial.md"
# picture on the page -> the file of a run that it is (the panel at the paper's strongest laser; a glob where a name
# carries what the run chose)
PICTURES = {
    "1_search_pareto.png": "outputs/tutorial/1_search/pareto.png",
    "2_psf_psf_log.png": "outputs/tutorial/2_psf/psf_log.png",
    "2_psf_mtf.png": "outputs/tutorial/2_psf/mtf.png",
    "3_simulate_sensor_grid_log.png": "outputs/tutorial/3_simulate/sensor_grid_log.png",
    "4_evaluate_panel.png": "outputs/tutorial/4_evaluate/panel_laser_1e6.png",
    "5_joint_compare.png": "outputs/tutorial/5_joint/compare_*.png",
    "6_export_report.png": "outputs/tutorial/6_export/report.png",
    "7_tolerance.png": "outputs/tutorial/7_tolerance/tolerance.png",
    "8_measured_psf.png": "outputs/tutorial/8_measured/measured_psf.png",
    "9_restored.png": "outputs/tutorial/9_restore/restored_*.png",
}


def commands(page: Path = PAGE) -> list[str]:
    """The commands of the page's ```bash blocks, one per block, in order."""
    blocks = re.findall(r"```bash\n(.*?)```", page.read_text(), flags=re.S)
    return [" ".join(line.rstrip("\\").strip() for line in b.strip().splitlines()) for b in blocks]


def run(root: Path, smoke: bool) -> None:
    for i, cmd in enumerate(commands(), 1):
        args = shlex.split(cmd)
        if args[:3] != ["python", "-m", "codesign"]:
            raise SystemExit(f"docs/tutorial.md: command {i} is not a codesign command: {cmd}")
        argv = [sys.executable, *args[1:], *(["debug=smoke"] if smoke else [])]
        print(f"[{i}/{len(commands())}] {cmd}{' debug=smoke' if smoke else ''}", flush=True)
        t0 = time.perf_counter()
        proc = subprocess.run(argv, cwd=root, capture_output=True, text=True)
        if proc.returncode != 0:
            print(proc.stdout[-3000:], proc.stderr[-6000:], sep="\n", file=sys.stderr)
            raise SystemExit(f"command {i} failed with exit code {proc.returncode}: {cmd}")
        print(f"      ok in {time.perf_counter() - t0:.0f} s", flush=True)


def collect(root: Path, pictures: Path) -> list[Path]:
    """Copy the page's pictures from the runs under ``root`` into ``pictures``; every one must exist."""
    pictures.mkdir(parents=True, exist_ok=True)
    out = []
    for name, pattern in PICTURES.items():
        found = sorted(root.glob(pattern))
        if not found:
            raise SystemExit(f"no {pattern} under {root}: the page's picture {name} has no source")
        shutil.copyfile(found[0], pictures / name)
        out.append(pictures / name)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--smoke", action="store_true", help="append debug=smoke to every command")
    ap.add_argument("--root", type=Path, default=REPO, help="folder the commands run in (default: the repository)")
    ap.add_argument("--pictures", type=Path, default=None, help="copy the page's pictures here")
    a = ap.parse_args(argv)
    a.root.mkdir(parents=True, exist_ok=True)
    if (a.root / "outputs" / "tutorial").exists():
        raise SystemExit(f"{a.root / 'outputs' / 'tutorial'} exists: a finished step is not run over; remove it "
                         "to run the tutorial again")
    run(a.root, a.smoke)
    if a.pictures is not None:
        for p in collect(a.root, a.pictures):
            print(f"wrote {p}")


if __name__ == "__main__":
    main()
