"""``python -m benchmarks.level_bound``: how well any restorer can know the scene's level (issue 35 item 3's plain
PSNR goal), measured on perfect restorations.

The sensor sees alpha_b * b with alpha_b ~ U[0.3, 0.7] (Sec. 6.2) drawn independently of the scene; the evaluation
scores against b at alpha_b = 0.7. Take a perfect restorer, whose output is alpha_b * b exactly: its plain PSNR is
then set by the gain it applies alone. Three gains, each chosen on training-split crops of the built-in scenes
(96 px, alpha_b drawn as in training), scored on the 12 photographs of ../shared/data/scenes (centre 96 px and the
whole 512 px) at alpha_b = 0.7:

- the best constant (least squares over the training crops: what a restorer that ignores the histogram learns);
- model.level_head's fit (codesign/models/level.py, the same features and ridge fit the network's head uses);
- the true 1 / alpha_b (infinite PSNR: the bound the other two are measured against).

    python -m benchmarks.level_bound --out benchmarks/results/level_bound.json
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from benchmarks.common import machine, write_json
from codesign.data.builtin import available_skimage_scenes
from codesign.data.images import find_image_files, load_image
from codesign.models.quality import psnr
from codesign.models.level import LevelHead, best_log_gain, fit_weight, level_features

SCENES = Path(__file__).resolve().parents[2] / "shared" / "data" / "scenes"
TEST_SPLIT = ("cell", "chelsea")  # the built-in test split: never trained on
ALPHA_B = (0.3, 0.7)
EVAL_ALPHA_B = 0.7


def training_crops(n_per_image: int, size: int, gen: torch.Generator) -> torch.Tensor:
    crops = []
    for name, path in sorted(available_skimage_scenes().items()):
        if name in TEST_SPLIT:
            continue
        img = torch.from_numpy(load_image(path)).double()
        h, w = img.shape
        for _ in range(n_per_image):
            y, x = (int(torch.randint(0, d - size + 1, (1,), generator=gen)) for d in (h, w))
            crops.append(img[y:y + size, x:x + size])
    return torch.stack(crops)[:, None]


def centre(img: torch.Tensor, size: int) -> torch.Tensor:
    h, w = img.shape
    return img[(h - size) // 2:(h - size) // 2 + size, (w - size) // 2:(w - size) // 2 + size]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--crops", type=int, default=200, help="training crops per built-in scene")
    p.add_argument("--size", type=int, default=96)
    p.add_argument("--scenes", type=Path, default=SCENES)
    a = p.parse_args(argv)
    if not a.scenes.is_dir():
        p.error(f"--scenes: no folder {a.scenes}")
    gen = torch.Generator().manual_seed(0)
    b = training_crops(a.crops, a.size, gen)
    alpha = ALPHA_B[0] + (ALPHA_B[1] - ALPHA_B[0]) * torch.rand(b.shape[0], generator=gen, dtype=torch.float64)
    seen = alpha[:, None, None, None] * b  # the perfect restorer's output: the scene at the sensor's level
    field = seen > 0
    constant = float((seen * b).sum() / (seen * seen).sum())
    head = LevelHead()
    head.set_weight(fit_weight(level_features(seen, seen), best_log_gain(seen, b, field)))
    result = {"machine": machine(), "training_crops": int(b.shape[0]), "crop_px": a.size, "alpha_b": ALPHA_B,
              "eval_alpha_b": EVAL_ALPHA_B, "constant_gain": round(constant, 4), "plain_psnr": {}}
    photos = [torch.from_numpy(load_image(f)).double() for f in find_image_files(a.scenes)]
    for size in (a.size, min(min(ph.shape) for ph in photos)):
        target = torch.stack([centre(ph, size) for ph in photos])[:, None]
        out = EVAL_ALPHA_B * target
        gain = head.gain(out, out)[:, None, None, None]
        row = {"sensor level": float(psnr(out.clamp(0, 1), target).mean()),
               "best constant": float(psnr((constant * out).clamp(0, 1), target).mean()),
               "level head": float(psnr((gain * out).clamp(0, 1), target).mean()),
               "head gain x alpha_b (1 = right)": [round(float(g) * EVAL_ALPHA_B, 3) for g in gain.flatten()]}
        result["plain_psnr"][f"{size} px"] = row
        print(f"{len(photos)} photographs, centre {size} px, alpha_b {EVAL_ALPHA_B}, a perfect restoration: plain "
              f"PSNR {row['sensor level']:.2f} dB as it is, {row['best constant']:.2f} with the best constant gain "
              f"({constant:.3f}), {row['level head']:.2f} with the level head", flush=True)
    write_json(a.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
