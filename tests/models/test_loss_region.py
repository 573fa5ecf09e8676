"""model.loss.region: the terms that compare with a target on the whole padded canvas or on the sensor's field."""
from __future__ import annotations

import pytest
import torch

from codesign.camera import field_of_view
from codesign.errors import ConfigError
from codesign.models.fill import field_size
from codesign.models.losses import LossWeights, charbonnier
from codesign.models.restorer import TrainContext
from codesign.models.sgan import _targets
from tests.train._util import tiny_trainer

N, P = 48, 64  # the tiny preset's field and canvas


def _losses(tmp_path, region: str):
    tr = tiny_trainer(tmp_path, "model=sgan_b_l1", f"model.loss.region={region}", steps=1, val_every=0,
                      checkpoint_every=0, image_every=0)
    batch = tr.data.train_batch(0)
    g = torch.Generator().manual_seed(1)
    b = 2  # tiny batch
    out = {"i_b": torch.rand(b, 1, P, P, generator=g, dtype=torch.float64).requires_grad_(),
           "b": [torch.rand(b, 1, P // 2, P // 2, generator=g, dtype=torch.float64).requires_grad_(),
                 torch.rand(b, 1, P, P, generator=g, dtype=torch.float64).requires_grad_()]}
    batch = {k: (v.double() if torch.is_tensor(v) and v.is_floating_point() else v) for k, v in batch.items()}
    terms = tr.model.generator_losses(batch, out, TrainContext(critics=list(tr.model.critics())))
    return tr, batch, out, terms


def test_the_field_is_the_sensors_centred_square_of_measured_pixels():
    s = torch.zeros(3, 1, P, P)
    s[:, :, 8:56, 8:56] = torch.rand(3, 1, N, N) + 0.01
    s[0, :, 8:56, 8:56] = 0  # a black image: the others still give the field
    s[1, :, 8, :] = 0  # a dark row inside one image's field
    assert field_size(s) == N
    assert field_size(s[:0]) == 0


def test_on_the_field_the_terms_are_the_canvas_terms_of_its_central_square_and_blind_outside(tmp_path):
    tr, batch, out, terms = _losses(tmp_path, "field")
    assert field_size(batch["sensor"]) == N
    targets, eps = _targets(batch, "exposure"), tr.model.weights.charbonnier_eps
    c = field_of_view
    rec1 = charbonnier(c(out["i_b"], N), c(batch["irradiance"], N), eps)
    rec2 = charbonnier(c(out["b"][0], N // 2), c(targets[0], N // 2), eps) + charbonnier(c(out["b"][1], N),
                                                                                         c(targets[1], N), eps)
    assert torch.allclose(terms["rec1"], rec1, rtol=1e-12) and torch.allclose(terms["rec2"], rec2, rtol=1e-12)
    terms["generator_total"].backward()
    for x, n in ((out["i_b"], N), (out["b"][0], N // 2), (out["b"][1], N)):
        assert bool((c(x.grad, n) != 0).all())  # every field pixel is compared
        c(x.grad, n).zero_()
        assert bool((x.grad == 0).all())  # and nothing outside it


def test_on_the_canvas_every_pixel_is_compared(tmp_path):
    tr, batch, out, terms = _losses(tmp_path, "canvas")
    targets, eps = _targets(batch, "exposure"), tr.model.weights.charbonnier_eps
    assert torch.allclose(terms["rec1"], charbonnier(out["i_b"], batch["irradiance"], eps), rtol=1e-12)
    assert torch.allclose(terms["rec2"], sum(charbonnier(out["b"][k], targets[k], eps) for k in range(2)),
                          rtol=1e-12)


def test_an_unknown_region_is_refused():
    with pytest.raises(ConfigError, match=r"^model.loss.region = 'all': must be one of canvas, field$"):
        LossWeights(region="all")
