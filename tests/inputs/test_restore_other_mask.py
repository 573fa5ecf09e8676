"""+experiment=restore (and the function it calls) with a typed mask other than the one the checkpoint's network was
trained on: a warning when the network cannot know the mask (trained on one, no data.masks pool, and not conditioned
on the mask); none for a restorer built for any mask (model=wiener_naf) or trained over a pool of masks. It went on
without a word."""
from __future__ import annotations

import logging
from types import SimpleNamespace

import pytest
from omegaconf import OmegaConf

from codesign.experiments import restore
from codesign.models.restorer import REGISTRY, restorer_kinds
from tests.inputs._run import WorkStarted, restore_messages

restorer_kinds()
SGAN = SimpleNamespace(kind="sgan", mask_conditioned=REGISTRY["sgan"].mask_conditioned)
NAF = SimpleNamespace(kind="wiener_naf", mask_conditioned=REGISTRY["wiener_naf"].mask_conditioned)
HALFRING = {"kind": "halfring", "preset": "published"}
SPLINE = {"kind": "spline", "init": "defocus"}


def _warned(caplog, model, own: dict, here: dict, typed=("mask",), masks=None, learned=None) -> list[str]:
    ckpt = OmegaConf.create({"mask": own, "data": {"masks": masks}})
    cfg = OmegaConf.create({"mask": here})
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="codesign"):
        said = restore.warn_other_mask(model, ckpt, {"mask": learned}, cfg, frozenset(typed), "ck.pt")
    messages = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert said == bool(messages)
    return messages


def test_a_network_trained_on_one_mask_restoring_through_another_is_warned(caplog):
    message, = _warned(caplog, SGAN, HALFRING, SPLINE)
    assert message == ("checkpoint ck.pt: its network (model.kind=sgan) was trained on a halfring mask only (no "
                       "data.masks pool) and is not conditioned on the mask; this run restores through the typed "
                       "mask=spline, which the network never saw: expect worse restorations (omit mask=... to restore "
                       "through the checkpoint's own mask, or use a restorer for any mask: checkpoint=pretrained, "
                       "model=wiener_naf)")
    # a co-designed checkpoint's network learned its learned mask: the configured one typed again is another
    message, = _warned(caplog, SGAN, HALFRING, HALFRING, learned={"r": [1.0]})
    assert "was trained on its learned (co-designed) mask only" in message


@pytest.mark.parametrize("case", ["no-mask-typed", "same-mask", "mask-conditioned", "trained-on-a-pool"])
def test_no_warning_where_the_network_knows_the_mask(caplog, case):
    kwargs = {"no-mask-typed": dict(typed=()), "same-mask": dict(here=HALFRING), "mask-conditioned": dict(model=NAF),
              "trained-on-a-pool": dict(masks=["published", "random:spline:4"])}[case]
    args = {"model": SGAN, "own": HALFRING, "here": SPLINE, **kwargs}
    assert _warned(caplog, args.pop("model"), args.pop("own"), args.pop("here"), **args) == []


def test_restore_warns_before_any_work(trained, tmp_path, monkeypatch, caplog):
    said = restore_messages(monkeypatch, caplog, tmp_path, trained, "mask=spline", stops=(WorkStarted, SystemExit))
    assert any("this run restores through the typed mask=spline, which the network never saw" in m for m in said)
