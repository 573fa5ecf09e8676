"""A mask-only search (+experiment=mask_search): the best design of a family under the LSR and MTF limits,
against the published mask and the physical limit.

    python examples/mask_search.py --smoke              # debug=smoke: 8 evaluations, seconds
    python examples/mask_search.py mask=spline search.max_evals=300   # any Hydra override
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
                    help="run folder (default: outputs/examples/mask_search/<date>_<time>, a new one each run)")
parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. mask=spline search.max_evals=300")
args = parser.parse_args()
args.out = args.out or Path("outputs/examples/mask_search") / time.strftime("%Y-%m-%d_%H-%M-%S")

found = codesign.mask_search(*args.overrides, *(["debug=smoke"] if args.smoke else []), run_dir=args.out)
print(f"searched the {found['mask_kind']} family: {found['evaluations']} evaluations, feasible={found['feasible']}")
print(f"best design: lsr={found['lsr']:.4e} mtf_mean={found['mtf_mean']:.4f} "
      f"(lsr_limit at its MTF {found['lsr_limit']:.4e})")
print(f"published mask: lsr={found['lsr_published']:.4e} mtf_mean={found['mtf_mean_published']:.4f}")
print(f"design record: {found['run_dir'] / 'best_mask.json'} (mask.init=PATH takes it)")
