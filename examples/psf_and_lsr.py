"""PSF and laser suppression ratio (LSR) of the published mask and of any other mask.

    python examples/psf_and_lsr.py                      # default optics (640-sample focal window), ~1 s
    python examples/psf_and_lsr.py --smoke              # debug=smoke optics (160-sample window)
    python examples/psf_and_lsr.py mask=zernike         # any Hydra override: another family, mask.init=PATH, ...
"""
import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's codesign, installed or not

import codesign  # noqa: E402

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--smoke", action="store_true", help="debug=smoke optics (seconds)")
parser.add_argument("overrides", nargs="*", help="Hydra overrides of the other mask, e.g. mask=spiral")
args = parser.parse_args()

cfg = codesign.compose(*args.overrides, *(["debug=smoke"] if args.smoke else []), experiment="psf")
system = codesign.optical_system(cfg)
spec = system.spec
print(f"optics: {spec.wavelength_m * 1e9:.0f} nm, f = {spec.focal_length_m * 1e3:.0f} mm, aperture "
      f"{spec.aperture_diameter_m * 1e3:.2f} mm, pupil {spec.grid_n} samples, window {spec.focal_n} x "
      f"{spec.focal_pitch_m * 1e6:.1f} um")

published = codesign.psf_and_lsr(codesign.published_mask(system, cfg), system, cfg)
print(f"published mask: lsr={published['lsr']:.4e} lsr_smooth={published['lsr_smooth']:.4e} "
      f"mtf_mean={published['mtf_mean']:.4f} bsr={published['bsr']:.4f} psf_peak={published['psf_peak']:.4e}")

mask = codesign.configured_mask(cfg, system)  # mask=<family> / mask.init=PATH; the published one by default
other = codesign.psf_and_lsr(mask, system, cfg)
print(f"configured {mask.kind} mask: lsr={other['lsr']:.4e} mtf_mean={other['mtf_mean']:.4f} "
      f"psf {tuple(other['psf'].shape)}, energy in window {other['psf_energy_in_window']:.4f}")
