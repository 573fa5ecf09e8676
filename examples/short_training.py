"""A short training of a restoration network on the published mask (+experiment=baseline), then its evaluation
against the sensor image and the classical Wiener filter.

    python examples/short_training.py --smoke           # debug=smoke: a tiny network, 4 steps, seconds
    python examples/short_training.py trainer.steps=200 # any Hydra override (model=sgan_f, preset=cpu, ...)
"""
import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's codesign, installed or not

import codesign  # noqa: E402

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--smoke", action="store_true", help="debug=smoke sizes (seconds)")
parser.add_argument("--out", type=Path,
                    help="run folder (default: outputs/examples/short_training/<date>_<time>, a new one each run)")
parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. trainer.steps=200 model=sgan_f")
args = parser.parse_args()
args.out = args.out or Path("outputs/examples/short_training") / time.strftime("%Y-%m-%d_%H-%M-%S")

trained = codesign.train_restorer(*args.overrides, *(["debug=smoke"] if args.smoke else []), run_dir=args.out)
print(f"trained {trained['steps']} steps in {trained['seconds']:.1f} s")
print(f"{trained['variant']} ({trained['size']} width, {trained['parameters_generators']} generator parameters), "
      f"{trained['image_size']} px images; PSNR on the test scenes (dB):")
for preset in sorted({k.rsplit("_", 2)[-2] + "_" + k.rsplit("_", 1)[-1] for k in trained
                      if k.startswith("psnr_sgan_laser_")}, key=lambda p: float(p.split("_")[1])):
    a = preset.split("_")[1]
    print(f"  alpha_l={a}: network psnr_sgan={trained[f'psnr_sgan_{preset}']:.2f}, sensor image "
          f"{trained[f'psnr_sensor_{preset}']:.2f}, Wiener {trained[f'psnr_wiener_{preset}']:.2f}")
print(f"checkpoint: {trained['run_dir'] / 'checkpoint.pt'} (codesign.restore(capture, checkpoint) takes it)")
