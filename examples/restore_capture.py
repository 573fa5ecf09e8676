"""Restore a dazzled capture with the shipped restorer, through a mask it never trained on, at any size.

The shipped restorer (``checkpoint=pretrained``, codesign/models/pretrained/README.md) takes the capture and the
OTF of the mask it came through, so one network restores any mask and any capture size. Here a capture of the
main job's designed mask (benchmarks/results/pretrained/heldout_mask.json.gz, held out of the restorer's training) is
simulated at the 256 px scale of the paper's 2532 x 2532 sensor (or, with --size, a non-square crop of it), written
as a 16-bit PNG, and restored by +experiment=restore (``restore.input_bin``: the capture is already binned).

    python examples/restore_capture.py                    # 256 x 256, alpha_l = 1e6
    python examples/restore_capture.py --size 192 256     # a non-square capture
"""
import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # this checkout's codesign, installed or not

import codesign  # noqa: E402
from codesign.io.captures import read_counts, save_png16  # noqa: E402

MASK = ROOT / "benchmarks" / "results" / "pretrained" / "heldout_mask.json.gz"

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--alpha-l", type=float, default=1e6, help="laser strength alpha_l (dimensionless)")
parser.add_argument("--size", type=int, nargs=2, default=(256, 256), metavar=("ROWS", "COLUMNS"),
                    help="the capture's size at the 256 px scale (a crop of the simulated 256 x 256 frame)")
parser.add_argument("--out", type=Path,
                    help="output folder (default: outputs/examples/restore_capture/<date>_<time>, a new one each run)")
args = parser.parse_args()
args.out = args.out or Path("outputs/examples/restore_capture") / time.strftime("%Y-%m-%d_%H-%M-%S")

cfg = codesign.checkpoint_config("pretrained")  # the shipped restorer's optics and sensor
cfg.data.image_size, cfg.data.padded_size = 256, 320  # the paper's 256 px scale of the 2532 px sensor
cfg.mask = {"kind": "spline", "init": str(MASK)}
sim = codesign.sensor_image(0, args.alpha_l, cfg)
rows, cols = args.size
top, left = (256 - rows) // 2, (256 - cols) // 2
counts = sim["sensor_dn"][0, 0, top:top + rows, left:left + cols]
capture = args.out / "captures" / f"sensor_alpha_l_{codesign.alpha_tag(args.alpha_l)}.png"
save_png16(capture, counts.cpu().numpy())
print(f"capture: {capture} ({rows} x {cols} px at bin {2532 / 256:.2f}, "
      f"{float(sim['saturated'].float().mean()):.4f} saturated)")

result = codesign.restore(capture, "pretrained", "mask=spline", f"mask.init={MASK}", f"restore.input_bin={2532 / 256}",
                          run_dir=args.out / "restore")
restored = read_counts(result["run_dir"] / result["outputs"][0]) / 65535.0  # 1 = the full well
m = (320 - 256) // 2  # the scene on the padded grid, the field centred
scene = sim["scene"][0, 0, m + top:m + top + rows, m + left:m + left + cols]
sensor = sim["sensor"][0, 0, m + top:m + top + rows, m + left:m + left + cols]
ours, raw = codesign.quality(restored, scene), codesign.quality(sensor, scene)
print(f"restored {result['outputs'][0]} ({restored.shape[0]} x {restored.shape[1]} px) in "
      f"{result['seconds_per_image']:.2f} s: PSNR after the gain/offset match {ours['psnr_matched']:.2f} dB "
      f"(sensor image {raw['psnr_matched']:.2f} dB)")
