"""A mask record of one family loaded into another (``mask=spline mask.init=<half-ring record>``) is fitted by the
configured family: how well is said (its RMS phase error), with a warning when the fit is not the design (a half-ring
record fitted by the spline family: its LSR went from 0.0086 to 0.053 without a word)."""
from __future__ import annotations

import json
import logging

import pytest
import torch

from codesign.optics import OpticsSpec
from codesign.optics.grid import PupilGrid
from codesign.optics.masks import PUBLISHED_R, PUBLISHED_THETA, build_mask

HALFRING = {"kind": "halfring", "r": list(PUBLISHED_R), "theta": list(PUBLISHED_THETA)}


@pytest.fixture(scope="module")
def grid():
    return PupilGrid.from_spec(OpticsSpec(pupil_pitch_m=4e-5, focal_n=64), dtype=torch.float64)


def _fitted(grid, tmp_path, caplog, kind: str, record: dict) -> list:
    path = tmp_path / f"{record['kind']}.json"
    path.write_text(json.dumps(record))
    coarse = {"control_spacing": 6.0} if kind == "spline" else {}  # a fit of a fraction of a second
    with caplog.at_level(logging.INFO, logger="codesign"):
        build_mask({"kind": kind, "init": str(path), **coarse}, grid, 3.83e-3)
    return [(r.levelno, r.getMessage()) for r in caplog.records if "fitted by" in r.getMessage()]


# the spline family's least-squares fit takes ~30 s under pytest on 2 cores: the Zernike case is the fast twin
@pytest.mark.parametrize("kind", [pytest.param("spline", marks=pytest.mark.slow), "zernike"])
def test_a_half_ring_record_a_family_cannot_represent_is_fitted_with_a_warning(grid, tmp_path, caplog, kind):
    (level, message), = _fitted(grid, tmp_path, caplog, kind, HALFRING)
    assert level == logging.WARNING
    assert message.startswith(f"mask.init {tmp_path / 'halfring.json'}: a halfring record fitted by the {kind} "
                              f"family: RMS phase error ")
    error = float(message.split("RMS phase error ")[1].split(" rad")[0])
    assert error > 1.0  # the half rings' steps: the smooth families cannot follow them
    assert message.endswith("above 0.25 rad: the mask is not the design (its PSF and LSR differ); build it as "
                            "designed with mask=halfring")


def test_a_record_a_family_represents_is_fitted_with_a_note_only(grid, tmp_path, caplog):
    (level, message), = _fitted(grid, tmp_path, caplog, "pixel", HALFRING)
    assert level == logging.INFO and "a halfring record fitted by the pixel family: RMS phase error 0 rad" in message
