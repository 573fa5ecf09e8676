"""WienerNAF (model=wiener_naf), the restorer conditioned on the OTF: its classical start against a float64 Wiener
reference, unit DC gain, any image size, tiled decoding equal to whole, gradients into the OTF (the mask's path in
co-design), colour channels, and the trainer and co-design running it."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from codesign.errors import ConfigError
from codesign.models import build_restorer
from codesign.models.fill import push_pull_fill, valid_pixels
from codesign.models.naf import NAFUNet
from codesign.models.wiener_naf import WienerNAF, WienerNAFSpec
from codesign.sensor.kernels import otf_from_kernel
from tests.train._util import joint_trainer, tiny_trainer


def _kernel(k: int = 7, sigma: float = 1.5) -> torch.Tensor:
    r = torch.arange(k, dtype=torch.float64) - k // 2
    g = torch.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * sigma**2))
    return g / g.sum()


def _capture(h: int = 40, w: int = 56, pad: int = 6, seed: int = 0) -> torch.Tensor:
    """A capture on its padded canvas: zero outside the field, a saturated spot inside."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.zeros(2, 1, h, w)
    x[..., pad:h - pad, pad:w - pad] = 0.05 + 0.6 * torch.rand(2, 1, h - 2 * pad, w - 2 * pad, generator=gen)
    x[0, 0, 15:19, 20:25] = 1.0
    return x


def _randomize(model: WienerNAF, seed: int = 1) -> None:
    """Every decoder weight drawn (the zero-initialized gates and output too): a decoder that does something."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.decoder.parameters():
            p.copy_(0.2 * torch.randn(p.shape, generator=gen))


def test_registered_and_checked():
    model = build_restorer({"kind": "wiener_naf", "size": "tiny"})
    assert isinstance(model, WienerNAF) and model.critics() == [] and model.method == "wiener_naf"
    with pytest.raises(ConfigError, match=r"^model\.bank_nsr = \[\]: must be a non-empty list of noise-to-signal "
                       r"ratios in \[1e-8, 1e3\]$"):
        build_restorer({"kind": "wiener_naf", "bank_nsr": []})
    with pytest.raises(ConfigError, match=r"^model\.fe_kernel = 4: must be odd \(same-size convolution\)$"):
        build_restorer({"kind": "wiener_naf", "fe_kernel": 4})
    with pytest.raises(ConfigError, match=r"^model\.channels = 0: "):
        build_restorer({"kind": "wiener_naf", "channels": 0})


def test_a_fresh_network_is_the_classical_wiener_of_the_filled_capture_at_unit_dc():
    """Decoder output zero at start, the base's mix made one-hot: restored = F^-1{Y conj(H) / (|H|^2 + nsr)}
    (H(0)^2 + nsr) / H(0) of the push-pull-filled capture, against numpy's float64 FFT."""
    model = WienerNAF(WienerNAFSpec(size="tiny")).double()
    pick = 2
    with torch.no_grad():
        model.front.mix.copy_(torch.where(torch.arange(4) == pick, 200.0, -200.0))
    x = _capture().double()
    otf = otf_from_kernel(0.9 * _kernel(), x.shape[-2:])  # H(0) = 0.9: the unit-DC factor matters
    out = model.restore(x, otf)["restored"].detach()
    filled = push_pull_fill(x, valid_pixels(x))[:, 0].numpy()
    h = np.fft.fft2(np.fft.irfft2(otf.numpy(), s=x.shape[-2:]))
    nsr = float(model.front.log_nsr.detach().exp()[pick])  # the bank's (float32-rounded) start value
    assert abs(nsr - WienerNAFSpec().bank_nsr[pick]) < 1e-7 * nsr
    ref = np.real(np.fft.ifft2(np.fft.fft2(filled) * h.conj() / (np.abs(h) ** 2 + nsr))) * (0.81 + nsr) / 0.9
    assert np.abs(out[:, 0].numpy() - ref).max() < 1e-12


def test_a_fresh_network_keeps_a_uniform_scene_level_through_any_mask():
    """Unit DC gain: a uniform capture filling the canvas comes back at its level, whatever the kernel."""
    model = WienerNAF(WienerNAFSpec(size="tiny"))
    x = torch.full((1, 1, 32, 48), 0.37)
    for kernel in (_kernel(9, 3.0), torch.rand(11, 11) + 0.01):
        out = model.restore(x, otf_from_kernel(kernel / kernel.sum(), (32, 48)))["restored"].detach()
        assert float((out - 0.37).abs().max()) < 1e-5


def test_any_size_and_a_clear_error_for_a_mismatched_otf():
    model = WienerNAF(WienerNAFSpec(size="tiny"))
    _randomize(model)
    for h, w in ((37, 53), (64, 24), (17, 17)):
        x = torch.rand(1, 1, h, w)
        assert model.restore(x, otf_from_kernel(_kernel(5), (h, w)))["restored"].shape == (1, 1, h, w)
    with pytest.raises(ValueError, match=r"^the OTF must be \(37, 27\) or \(1, 37, 27\) for a 37 x 53 sensor image "
                       r"\(rfft2 of the PSF kernel on the same grid\), got \(37, 37\)$"):
        model.restore(torch.rand(1, 1, 37, 53), otf_from_kernel(_kernel(5), (37, 72)))


def test_tiled_decoding_equals_the_whole_image():
    model = WienerNAF(WienerNAFSpec(size="tiny"))
    _randomize(model)
    x = _capture(72, 100, pad=8)
    otf = otf_from_kernel(_kernel(9, 2.0), x.shape[-2:])
    whole = model.restore(x, otf)["restored"]
    calls = []
    tiled = model.restore_tiled(x, otf, tile=16, progress=lambda i, n: calls.append((i, n)))
    assert float((tiled - whole).abs().max()) < 1e-5 * float(whole.abs().max())
    assert calls[-1] == (35, 35) and len(calls) == 35  # ceil(72 / 16) x ceil(100 / 16) tiles


def test_the_decoder_is_local_within_its_reach():
    net = NAFUNet(3, 1, 4, (1, 1), 1, (1, 1))
    for p in net.parameters():
        torch.nn.init.normal_(p, std=0.3)
    x = torch.rand(1, 3, 96, 96)
    y = x.clone()
    y[..., 0, 0] += 10.0  # a change at one corner
    r = net.reach
    d = (net(x) - net(y)).abs()[0, 0]
    assert float(d[r + 8:, :].max()) == 0.0 and float(d[:, r + 8:].max()) == 0.0  # +8: the downsampling grid
    assert float(d[0, 0]) > 0


def test_the_psf_takes_gradient_float64():
    """gradcheck through the whole restorer in float64 with respect to the capture and the PSF kernel the OTF is
    made of (co-design's path to the mask: the bank and the feature deconvolution read the OTF). (The rfft layout's
    redundant entries make a gradcheck in the OTF itself ill-posed: the kernel is the real input.)"""
    torch.manual_seed(0)
    model = WienerNAF(WienerNAFSpec(size="tiny", fe_features=2, bank_nsr=(1e-2, 1e-1))).double()
    _randomize(model)
    x = (0.1 + 0.5 * torch.rand(1, 1, 8, 12, dtype=torch.float64))
    kernel = _kernel(3, 0.8).requires_grad_(True)
    restore = lambda s, k: model(s, otf_from_kernel(k, (8, 12)))["restored"]  # noqa: E731
    assert torch.autograd.gradcheck(restore, (x.clone().requires_grad_(True), kernel), eps=1e-6, atol=1e-6)
    # with a padding row (exactly 0: not measured, filled): the capture's zeros are a boundary, the kernel is smooth
    x[..., 0, :] = 0.0
    assert torch.autograd.gradcheck(lambda k: restore(x, k), (kernel,), eps=1e-6, atol=1e-6)


def test_colour_channels_each_take_their_own_otf():
    """channels=3 with one OTF per channel: a fresh network's base is each channel's own Wiener (here: a channel
    through a sharp kernel against one through a blur)."""
    model = WienerNAF(WienerNAFSpec(size="tiny", channels=3))
    x = torch.rand(2, 3, 24, 32) * 0.5 + 0.1
    delta = torch.zeros(5, 5)
    delta[2, 2] = 1.0
    otfs = torch.stack([otf_from_kernel(k.float(), (24, 32)) for k in (delta, _kernel(5), _kernel(5, 0.7))])
    out = model.restore(x, otfs)["restored"]
    assert out.shape == (2, 3, 24, 32)
    single = WienerNAF(WienerNAFSpec(size="tiny"))
    single.front.load_state_dict(model.front.state_dict())
    for c in range(3):
        ref = single.restore(x[:, c:c + 1], otfs[c])["base"]
        assert torch.allclose(model.restore(x, otfs)["base"][:, c:c + 1], ref, atol=1e-6)


def test_the_trainer_trains_it_and_co_design_moves_the_mask_through_it(tmp_path):
    torch.manual_seed(0)
    tr = tiny_trainer(tmp_path, "model=wiener_naf", "model.size=tiny", "trainer.lr_weights=5e-4",
                      "trainer.lr_biases=5e-4")
    val = tr.data.validation_batch(4)

    def val_loss() -> float:
        with torch.no_grad():
            return float(tr.model.generator_losses(val, tr.model.restore(val["sensor"], tr.data.otf), None)["rec2"])

    before = val_loss()
    assert set(tr.train_step()) == {"rec2", "generator_total", "generator_skipped"}
    for _ in range(29):
        tr.train_step()
    assert val_loss() < 0.97 * before  # measured: 0.942 of it (a fresh network is the classical Wiener)
    jt = joint_trainer(tmp_path / "joint", "model=wiener_naf", "model.size=tiny", mask_lr=0.5)
    before = [p.detach().clone() for p in jt.codesign.params]
    jt.train_step()
    assert any(not torch.equal(a, b.detach()) for a, b in zip(before, jt.codesign.params))
