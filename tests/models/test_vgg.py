"""VGG feature extractor: torchvision index layout, loading a user state dict, and its error messages."""
from __future__ import annotations

import pytest
import torch
import torch.nn as nn

from codesign.errors import ConfigError
from codesign.models.vgg import (ImageNetInput, extract, layer_index, load_vgg_features, vgg16_features,
                                 vgg19_features)


def random_state_dict(build, seed: int = 0) -> dict[str, torch.Tensor]:
    """He-scaled random weights at the real shapes of ``build()`` under torchvision's ``features.`` names, plus a
    classifier key."""
    g = torch.Generator().manual_seed(seed)
    sd = {}
    with torch.device("meta"):  # shapes only
        shapes = build().state_dict()
    for k, v in shapes.items():
        fan_in = v[0].numel() if v.ndim > 1 else 1
        sd[f"features.{k}"] = torch.randn(v.shape, generator=g) * (2 / fan_in) ** 0.5 * (v.ndim > 1)
    sd["classifier.0.weight"] = torch.zeros(4, 3)
    return sd


@pytest.fixture(scope="module")
def vgg19_file(tmp_path_factory):
    sd = random_state_dict(vgg19_features)
    path = tmp_path_factory.mktemp("vgg") / "vgg19.pth"
    torch.save(sd, path)
    return path, sd


def test_torchvision_index_layout():
    with torch.device("meta"):
        f19, f16 = vgg19_features(), vgg16_features()
    assert len(f19) == 37 and len(f16) == 31
    convs19 = [i for i, m in enumerate(f19) if isinstance(m, nn.Conv2d)]
    assert convs19 == [0, 2, 5, 7, 10, 12, 14, 16, 19, 21, 23, 25, 28, 30, 32, 34]
    assert [i for i, m in enumerate(f19) if isinstance(m, nn.MaxPool2d)] == [4, 9, 18, 27, 36]
    assert all(isinstance(f19[i + 1], nn.ReLU) for i in convs19)
    assert [i for i, m in enumerate(f16) if isinstance(m, nn.Conv2d)] == [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24,
                                                                          26, 28]
    assert [layer_index("vgg19", n) for n in ("relu1_2", "relu2_2", "relu3_4", "relu4_4", "relu5_4")] == \
        [3, 8, 17, 26, 35]
    assert [layer_index("vgg16", n) for n in ("relu1_2", "relu2_2", "relu3_3", "relu4_3", "relu5_3")] == \
        [3, 8, 15, 22, 29]
    assert sum(p.numel() for p in f19.parameters()) == 20024384  # torchvision's vgg19().features
    with pytest.raises(ConfigError, match="relu3_4"):
        layer_index("vgg19", "relu9_9")


def test_round_trip_frozen_eval(vgg19_file):
    path, sd = vgg19_file
    f = load_vgg_features("vgg19", path)
    assert not f.training and all(not p.requires_grad for p in f.parameters())
    for k, v in f.state_dict().items():
        assert torch.equal(v, sd[f"features.{k}"])
    x = torch.rand(1, 3, 32, 32)
    (a, b) = extract(f, x, [3, 35])
    assert a.shape == (1, 64, 32, 32) and b.shape == (1, 512, 2, 2)
    assert torch.equal(a, f[:4](x))


def test_missing_file_names_path(tmp_path):
    missing = tmp_path / "nowhere" / "vgg19.pth"
    with pytest.raises(ConfigError) as e:
        load_vgg_features("vgg19", missing)
    assert str(missing) in str(e.value) and "model.loss.vgg_weights" in str(e.value) and "not found" in str(e.value)


def test_not_a_state_dict(tmp_path):
    p = tmp_path / "list.pth"
    torch.save([torch.zeros(1)], p)
    with pytest.raises(ConfigError, match="not a state dict"):
        load_vgg_features("vgg19", p)
    p2 = tmp_path / "garbage.pth"
    p2.write_bytes(b"not a torch file")
    with pytest.raises(ConfigError, match="cannot be read"):
        load_vgg_features("vgg19", p2)


def test_missing_key_and_wrong_shape(tmp_path):
    # VGG16-sized file read as VGG19: the first VGG19 tensor VGG16 lacks is features.16.weight
    sd16 = random_state_dict(vgg16_features)
    p = tmp_path / "vgg16.pth"
    torch.save(sd16, p)
    with pytest.raises(ConfigError) as e:
        load_vgg_features("vgg19", p)
    assert "'features.16.weight'" in str(e.value) and "missing" in str(e.value) and "(256, 256, 3, 3)" in str(e.value)
    assert load_vgg_features("vgg16", p)[0].weight.shape == (64, 3, 3, 3)  # but it is a valid VGG16

    sd16["features.2.weight"] = torch.zeros(64, 64, 5, 5)
    torch.save(sd16, p)
    with pytest.raises(ConfigError) as e:
        load_vgg_features("vgg16", p)
    msg = str(e.value)
    assert "'features.2.weight'" in msg and "(64, 64, 5, 5)" in msg and "expected (64, 64, 3, 3)" in msg


def test_imagenet_input():
    x = torch.rand(2, 1, 5, 6)
    z = ImageNetInput()(x)
    assert z.shape == (2, 3, 5, 6)
    torch.testing.assert_close(z[:, 1:2], (x - 0.456) / 0.224)
    assert len(ImageNetInput().state_dict()) == 0  # constants, not weights
