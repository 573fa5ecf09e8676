"""Restore a dazzled capture with a trained network.

The checkpoint is the one the repository ships (benchmarks/results/gpu/checkpoint.pt: SGAN-B at the cpu width,
256 px, trained for 305 steps on one H100, docs/gpu.md; it learns but is not yet better than the raw sensor
image). With --train, or when that file is missing, a tiny network is trained first at smoke size (4 steps,
seconds: the restoration then shows the path, not a useful result). The capture is simulated with the
checkpoint's own optics, mask, sensor and image size, written as a 16-bit PNG, and restored by
+experiment=restore.

    python examples/restore_capture.py                  # the shipped checkpoint
    python examples/restore_capture.py --train          # a tiny network trained here first
"""
import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # this checkout's codesign, installed or not

import codesign  # noqa: E402
from codesign.camera import field_of_view  # noqa: E402
from codesign.io.captures import read_counts, save_png16  # noqa: E402

SHIPPED = ROOT / "benchmarks" / "results" / "gpu" / "checkpoint.pt"

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--train", action="store_true", help="train a tiny network first (debug=smoke)")
parser.add_argument("--alpha-l", type=float, default=1e6, help="laser strength alpha_l (dimensionless)")
parser.add_argument("--out", type=Path, default=Path("outputs/examples/restore_capture"), help="output folder")
args = parser.parse_args()

if args.train or not SHIPPED.is_file():
    trained = codesign.train_restorer("debug=smoke", run_dir=args.out / "train")
    checkpoint = trained["run_dir"] / "checkpoint.pt"
    print(f"trained a tiny network for {trained['steps']} steps: {checkpoint}")
else:
    checkpoint = SHIPPED
    print(f"the shipped checkpoint: {checkpoint}")

cfg = codesign.checkpoint_config(checkpoint)  # capture at the checkpoint's optics, mask, sensor and image size
sim = codesign.sensor_image(0, args.alpha_l, cfg)
capture = args.out / "captures" / f"sensor_alpha_l_{codesign.alpha_tag(args.alpha_l)}.png"
save_png16(capture, sim["sensor_dn"][0, 0].cpu().numpy())
print(f"capture: {capture} ({cfg.data.image_size} px, {float(sim['saturated'].float().mean()):.4f} saturated)")

result = codesign.restore(capture, checkpoint, run_dir=args.out / "restore")
restored = read_counts(result["run_dir"] / result["outputs"][0]) / 65535.0  # radiance in [0, 1]
n = int(cfg.data.image_size)  # the targets are on the padded grid (data.padded_size), the image centred
target = field_of_view(sim["scene"], n)[0, 0].cpu().numpy()
sensor = field_of_view(sim["sensor"], n)[0, 0].cpu().numpy()


def psnr(x: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((x - target) ** 2)))


print(f"restored {result['outputs'][0]} in {result['seconds_per_image']:.2f} s: PSNR against the scene "
      f"{psnr(restored):.2f} dB (sensor image {psnr(sensor):.2f} dB)")
