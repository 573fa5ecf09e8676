"""The held-out photographs shipped for evaluation only: what they are, where they come from, and that evaluation
uses them by default."""
from __future__ import annotations

import re

import numpy as np
import pytest
from PIL import Image

from codesign.data.scenes import HELDOUT_DIR, builtin_scene_names, heldout_source
from codesign.errors import ConfigError
from codesign.train.evaluation import EvaluateSpec

LICENCES = {"CC-BY-SA-3.0", "Unsplash License"}


def _table() -> dict[str, list[str]]:
    rows = re.findall(r"^\| (\w+\.png) \| (.+) \|$", (HELDOUT_DIR / "SOURCES.md").read_text(), flags=re.M)
    return {name: [c.strip() for c in rest.split(" | ")] for name, rest in rows}


def test_at_least_twelve_grayscale_photographs_each_with_its_source_and_licence():
    files = sorted(p.name for p in HELDOUT_DIR.glob("*.png"))
    table = _table()
    assert len(files) >= 12 and sorted(table) == files
    for name in files:
        img = Image.open(HELDOUT_DIR / name)
        assert img.mode == "L" and img.size == (512, 512), name
        pixels = np.asarray(img, dtype=np.float64)
        assert pixels.std() > 10, name  # a photograph, not a flat field
        package, original, author, licence = table[name][:4]
        assert licence in LICENCES and original and author and package, name


def test_disjoint_from_the_built_in_scenes_and_read_as_one_split():
    source = heldout_source()
    assert source.split_names("all") == sorted(p.name for p in HELDOUT_DIR.glob("*.png"))
    stems = {n.rsplit(".", 1)[0] for n in source.names}
    assert not stems & set(builtin_scene_names())
    batch = source.fixed_batch(source.names[:3], 128)
    assert batch.shape == (3, 1, 128, 128) and 0.0 <= float(batch.min()) and float(batch.max()) <= 1.0


def test_evaluation_scores_them_by_default():
    spec = EvaluateSpec()
    assert spec.scenes == "heldout" and spec.max_scenes >= len(_table())
    with pytest.raises(ConfigError, match=r"^evaluate.scenes = 'test': must be one of heldout, data$"):
        EvaluateSpec(scenes="test")
