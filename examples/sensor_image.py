"""A simulated sensor image of a built-in scene, without and with a laser, through the published mask.

    python examples/sensor_image.py                     # default config (the laser's halo on the whole sensor)
    python examples/sensor_image.py --smoke             # debug=smoke sizes (seconds)
    python examples/sensor_image.py --alpha-l 1e4 --scene 1 --out captures/   # also write 16-bit PNG captures
"""
import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's codesign, installed or not

import codesign  # noqa: E402
from codesign.io.captures import save_png16  # noqa: E402

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--smoke", action="store_true", help="debug=smoke sizes (seconds)")
parser.add_argument("--alpha-l", type=float, default=1e6, help="laser strength alpha_l (dimensionless, 0: none)")
parser.add_argument("--scene", default="0", help="a scene name or an index into the test split")
parser.add_argument("--out", type=Path, help="folder for the 16-bit PNG captures (sensor counts, DN)")
parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. mask=spiral data.image_size=256")
args = parser.parse_args()

cfg = codesign.compose(*args.overrides, *(["debug=smoke"] if args.smoke else []), experiment="simulate")
scene = int(args.scene) if args.scene.lstrip("-").isdigit() else args.scene
cam = codesign.build_camera(cfg)  # built once: its PSF is computed once for both images
print(f"camera: {cam.mask.kind} mask, {cam.image_size} x {cam.image_size} px network image "
      f"({cam.sensor.coarse_pitch_m * 1e6:.2f} um pixels), scene crop {cam.scene_size} px; "
      f"test scenes {codesign.scene_names(cfg)[:4]}")
full_scale = cam.sensor.gain_dn_per_e * cam.sensor.full_well_e
for alpha_l in (0.0, args.alpha_l):
    out = codesign.sensor_image(scene, alpha_l, cfg, cam=cam)
    dn = out["sensor_dn"]
    print(f"alpha_l={codesign.alpha_tag(alpha_l)}: mean={float(dn.mean()):.1f} DN max={float(dn.max()):.1f} DN "
          f"(full scale {full_scale:.0f} DN) saturated_fraction={float(out['saturated'].float().mean()):.4f} "
          f"laser_peak={float(out['laser'].max()):.4g}")
    if args.out is not None:
        path = args.out / f"sensor_alpha_l_{codesign.alpha_tag(alpha_l)}.png"
        save_png16(path, dn[0, 0].cpu().numpy())
        print(f"wrote {path}")
