"""AttentionDescriptor: shapes, determinism, composition, intermediates, errors (random weights, no files)."""
from __future__ import annotations

import importlib

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from attnloop import AttentionDescriptor, DescriptorParts
from attnloop.descriptor import DescriptorRecipe, descriptor_from_attention
from attnloop.fusion import FUSION_MODES, fuse
from attnloop.guided_backprop import guided_backprop
from attnloop.rnn_pool import random_rnn_pool


@pytest.fixture(scope="module")
def images():
    g = torch.Generator().manual_seed(1)
    return torch.randint(0, 256, (3, 3, 120, 160), dtype=torch.uint8, generator=g)


@pytest.fixture(scope="module")
def lite():
    # the paper's flat RNN pooling at stage7 (224 x 224), with the pool-input scaling
    return AttentionDescriptor("efficientnet_lite0", fusion="dam", pretrained=False, seed=0, tap="stage7",
                               pooling="flat", num_rnn=16)


@pytest.mark.parametrize("fusion", FUSION_MODES)
def test_shapes_unit_norm_all_fusions(lite, images, fusion):
    desc = AttentionDescriptor(lite.backbone, fusion=fusion, seed=0)
    d = desc(images)
    assert d.shape == (3, 5 * 320) and d.dtype == torch.float32  # no RNNs: the regional code of stage7
    assert desc.out_dim == 5 * 320 and desc.pool is None and desc.rnn_weights is None
    assert torch.isfinite(d).all()
    assert torch.allclose(d.norm(dim=1), torch.ones(3), atol=1e-5)


def test_vgg16_random_weights_end_to_end(images):
    desc = AttentionDescriptor("vgg16", fusion="gaf", pretrained=False, seed=0, preset="paper")
    assert desc.pool.weights.shape == (16, 64, 256 * 7 * 7)  # the paper's 16 RNNs of 64 x 12544
    parts = desc.parts(images[:1])
    assert parts.tap.shape == (1, 512, 7, 7) and parts.descriptor.shape == (1, 1024)
    assert desc.out_dim == 1024


def test_same_seed_identical_different_seed_different(images):
    a = AttentionDescriptor("efficientnet_lite0", pretrained=False, seed=0)(images)
    b = AttentionDescriptor("efficientnet_lite0", pretrained=False, seed=0)(images)
    c = AttentionDescriptor("efficientnet_lite0", pretrained=False, seed=1)(images)
    assert torch.equal(a, b)
    # another seed: other random backbone weights (no RNNs by default), nearly orthogonal descriptors
    assert (a * c).sum(1).abs().max() < 0.5


def test_same_seed_same_rnn_for_a_given_backbone(lite, images):
    a = AttentionDescriptor(lite.backbone, seed=7, num_rnn=16)
    b = AttentionDescriptor(lite.backbone, seed=7, num_rnn=16)
    assert torch.equal(a.pool.weights, b.pool.weights)
    assert not torch.equal(a.pool.weights, lite.pool.weights)


def test_parts_are_consistent(lite, images):
    parts = lite.parts(images)
    assert isinstance(parts, DescriptorParts)
    net = lite.backbone
    with torch.no_grad():
        tap = net.forward_to_tap(net.preprocess(images))
    assert torch.allclose(parts.tap, tap, atol=1e-6)
    assert parts.grad.shape == parts.tap.shape == (3, 320, 7, 7)
    # random weights: a flat softmax, so G is tiny (below minmax_normalize's 1e-12 constant-map
    # threshold); the descriptor fuses G / max|G|, which the fusions cannot tell from G otherwise.
    assert parts.grad.abs().max() < 1e-9
    peak = parts.grad.abs().amax(dim=(1, 2, 3), keepdim=True)
    assert torch.allclose(parts.fused, fuse(parts.tap, parts.grad / peak, "dam"))
    assert parts.fused.abs().sum() > 0
    # descriptor = L2(pool(10 * fused / |fused|)), computed here without the library's helper
    x = parts.fused.flatten(1)
    x = (10.0 * x / x.norm(dim=1, keepdim=True)).view_as(parts.fused)
    ref = F.normalize(random_rnn_pool(x, lite.pool.weights), dim=1)
    assert torch.allclose(parts.descriptor, ref, atol=1e-6)
    assert torch.allclose(lite(images), parts.descriptor)
    assert torch.allclose(lite.from_attention(parts.tap, parts.grad), parts.descriptor)


def test_batch_equals_single_frames(lite, images):
    d = lite(images)
    for i in range(images.shape[0]):
        assert torch.allclose(lite(images[i:i + 1]), d[i:i + 1], atol=1e-5)


def test_uint8_and_float_images_agree(lite, images):
    a = lite(images)
    b = lite(images.float() / 255.0)
    assert ((a * b).sum(1) > 0.999).all()


def test_no_grad_and_inference_mode(lite, images):
    ref = lite(images)
    with torch.no_grad():
        a = lite(images)
    with torch.inference_mode():
        b = lite(images)
    assert torch.equal(ref, a) and torch.equal(ref, b)
    assert all(p.grad is None for p in lite.parameters())


def test_composes_in_a_users_sequential(images):
    torch.manual_seed(0)
    model = nn.Sequential(
        AttentionDescriptor("efficientnet_lite0", fusion="ega", pretrained=False, seed=0),
        nn.Linear(5 * 112, 10),  # 5 regions of Lite0's stage5, 112 channels
    )
    out = model(images)
    assert out.shape == (3, 10)
    out.logsumexp(1).sum().backward()  # the user's head trains; the descriptor is a frozen extractor
    assert model[1].weight.grad is not None and model[1].weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in model[0].parameters())
    trainable = [n for n, p in model.named_parameters() if p.requires_grad]
    assert trainable == ["1.weight", "1.bias"]
    model.train()
    assert model[0].training and not model[0].backbone.training  # batch-norm stays frozen
    assert not any(k.startswith("0.pool") for k in model.state_dict())  # no RNNs by default
    rnns = AttentionDescriptor("efficientnet_lite0", pretrained=False, num_rnn=16)
    assert "pool.weights" in rnns.state_dict()  # the paper's RNN weights travel with the model


def test_empty_batch(lite):
    d = lite(torch.zeros(0, 3, 480, 640, dtype=torch.uint8))
    assert d.shape == (0, 1024)
    parts = lite.parts(torch.zeros(0, 3, 480, 640, dtype=torch.uint8))
    assert parts.tap.shape == (0, 320, 7, 7)


def test_raw_pool_input_option(lite, images):
    desc = AttentionDescriptor(lite.backbone, fusion="none", pool_scale=None, pooling="flat", num_rnn=16)
    parts = desc.parts(images)
    ref = F.normalize(random_rnn_pool(parts.tap, desc.pool.weights), dim=1)
    assert torch.allclose(parts.descriptor, ref, atol=1e-6)
    unnormalised = AttentionDescriptor(lite.backbone, fusion="none", normalize=False, pooling="flat",
                                       num_rnn=16)(images)
    assert (unnormalised.abs() <= 1).all() and not torch.allclose(unnormalised.norm(dim=1), torch.ones(3))


def test_functional_form_matches_module(lite, images):
    tap, grad = guided_backprop(lite.backbone, images)
    _fused, d = descriptor_from_attention(tap, grad, lite.pool.weights, fusion="dam", pooling="flat")
    assert torch.allclose(d, lite(images))
    _fused, d2 = descriptor_from_attention(torch.zeros(1, 320, 7, 7), torch.ones(1, 320, 7, 7),
                                          lite.pool.weights, "gaf", pooling="flat")
    assert torch.equal(d2, torch.zeros(1, 1024))  # a zero map gives a zero descriptor, not NaN


@pytest.mark.parametrize(
    "bad, err",
    [
        (torch.zeros(3, 120, 160, dtype=torch.uint8), "shape \\(B, 3, H, W\\)"),
        (torch.zeros(1, 4, 120, 160, dtype=torch.uint8), "shape \\(B, 3, H, W\\)"),
        (torch.zeros(1, 3, 120, 160, dtype=torch.int64), "uint8"),
        (torch.zeros(1, 3, 120, 160, device="meta"), "move one of them"),
    ],
)
def test_wrong_input(lite, bad, err):
    with pytest.raises(ValueError, match=err):
        lite(bad)


def test_wrong_settings(lite):
    with pytest.raises(ValueError, match="unknown fusion"):
        AttentionDescriptor(lite.backbone, fusion="sum")
    with pytest.raises(ValueError, match="unknown backbone"):
        AttentionDescriptor("resnet50", pretrained=False)
    with pytest.raises(ValueError, match="pool_scale"):
        AttentionDescriptor(lite.backbone, pool_scale=0.0)
    with pytest.raises(TypeError, match="lacks 'preprocess'"):
        AttentionDescriptor(nn.Linear(2, 2))
    with pytest.raises(ValueError, match="tap must have shape \\(B, 320, 7, 7\\)"):
        lite.from_attention(torch.zeros(1, 512, 7, 7), torch.zeros(1, 512, 7, 7))


def _small_classifier():
    torch.manual_seed(0)
    return nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2), nn.Conv2d(8, 16, 3, padding=1),
                         nn.ReLU(), nn.AdaptiveAvgPool2d(4), nn.Flatten(), nn.Linear(256, 10))


@pytest.mark.parametrize("build", ["default", "paper", "hooked"])
def test_none_runs_the_network_to_the_tap_only(images, monkeypatch, build):
    # "none" never reads G: no head, no seeded backward, and the descriptor parts() gives, exactly.
    net = _small_classifier()
    if build == "hooked":
        desc = AttentionDescriptor(net, fusion="none", tap="4", input_size=(32, 32), seed=0)
    else:
        desc = AttentionDescriptor("efficientnet_lite0", fusion="none", pretrained=False, seed=0,
                                   **({"preset": "paper"} if build == "paper" else {}))
    want = desc.parts(images).descriptor
    module = importlib.import_module("attnloop.descriptor")

    def no_backward(*args, **kwargs):
        raise AssertionError("fusion='none' computed G")

    monkeypatch.setattr(module, "guided_backprop", no_backward)
    head_calls = []
    head = desc.backbone._fc if build != "hooked" else net[7]
    handle = head.register_forward_hook(lambda *a: head_calls.append(1))
    try:
        got = desc(images)
        assert torch.equal(got, want) and not head_calls
        assert desc(images[:0]).shape == (0, desc.out_dim)
    finally:
        handle.remove()
    with pytest.raises(AssertionError, match="computed G"):
        AttentionDescriptor(desc.backbone, fusion="dam", seed=0)(images)  # the others still need G


def test_default_has_no_rnns_the_regional_code_is_the_descriptor(lite, images):
    # num_rnn=0 (the default): the descriptor is the fused map's regional code, L2-normalised, computed
    # here by hand (GeM p = 3 over the whole map and a 2 x 2 grid, each region L2-normalised)
    desc = AttentionDescriptor(lite.backbone, fusion="gaf")
    parts = desc.parts(images)
    x = parts.fused / parts.fused.abs().amax((1, 2, 3), keepdim=True)
    x = x.clamp_min(1e-6) ** 3
    h, w = x.shape[2:]
    cells = [(slice(0, h), slice(0, w))] + [(slice(a, b), slice(c, d)) for a, b in ((0, (h + 1) // 2), (h // 2, h))
                                            for c, d in ((0, (w + 1) // 2), (w // 2, w))]
    regions = [F.normalize(x[:, :, r, c].mean((2, 3)) ** (1 / 3), dim=1) for r, c in cells]
    ref = F.normalize(torch.cat(regions, 1), dim=1)
    assert parts.descriptor.shape == (3, 5 * 320)
    assert torch.allclose(parts.descriptor, ref, atol=1e-6)
    assert torch.allclose(desc(images), ref, atol=1e-6)
    assert desc.recipe.out_dim is None and desc.out_dim == 1600
    # the functional form with no RNN weights is the same descriptor
    _f, d = descriptor_from_attention(parts.tap, parts.grad, None, "gaf")
    assert torch.allclose(d, ref, atol=1e-6)
    empty = desc(torch.zeros(0, 3, 64, 64, dtype=torch.uint8))
    assert empty.shape == (0, 1600) and empty.dtype == torch.float32


@pytest.mark.parametrize("kwargs, name", [({"out_features": 32}, "out_features"), ({"pool_scale": None}, "pool_scale"),
                                          ({"merge": True}, "merge"), ({"pool_scale": 3.0}, "pool_scale")])
def test_rnn_settings_without_rnns_are_refused(lite, kwargs, name):
    # a setting that would do nothing is an error, not silently ignored
    with pytest.raises(ValueError, match=f"{name} set the random RNNs, and num_rnn=0 has none"):
        AttentionDescriptor(lite.backbone, **kwargs)
    AttentionDescriptor(lite.backbone, num_rnn=16, **kwargs)  # with RNNs they apply
    with pytest.raises(ValueError, match="num_rnn must be a non-negative integer"):
        AttentionDescriptor(lite.backbone, num_rnn=-1)
    if name in ("pool_scale", "merge"):  # the functional form names the same setting, and only it
        with pytest.raises(ValueError, match=f"^{name} set the random RNNs' input, and rnn_weights=None has no RNNs"):
            descriptor_from_attention(torch.rand(1, 320, 7, 7), torch.rand(1, 320, 7, 7), None, "dam", **kwargs)


@pytest.mark.parametrize("kwargs, error, match", [
    ({"seed": 1.5}, ValueError, "seed must be a non-negative integer, got 1.5"),
    ({"seed": -1}, ValueError, "seed must be a non-negative integer, got -1"),
    ({"seed": "0"}, ValueError, "seed must be a non-negative integer, got '0'"),
    ({"seed": True}, ValueError, "seed must be a non-negative integer, got True"),
    ({"num_rnn": 2.5}, ValueError, "num_rnn must be a non-negative integer, got 2.5"),
    ({"normalize": "no"}, TypeError, "normalize must be True or False, got 'no'"),
])
def test_recipe_refuses_values_it_would_misread(kwargs, error, match):
    # seed=1.5 used to give seed 1's RNN weights under a recipe that compared unequal to seed 1's; a string
    # flag was truthy whatever it said
    with pytest.raises(error, match=match):
        DescriptorRecipe(**kwargs)
    assert DescriptorRecipe(num_rnn=16.0, seed=3).out_dim == 1024  # a whole float count is still a count


@pytest.mark.parametrize("name", ["differentiable", "pretrained"])
def test_descriptor_flags_must_be_booleans(name):
    with pytest.raises(TypeError, match=f"{name} must be True or False, got 'False'"):
        AttentionDescriptor("efficientnet_lite0", **{name: "False"})


def test_what_applies_without_rnns(lite, images):
    # merge=False merges nothing, as without RNNs: accepted; the flat map is the RNNs' input: refused
    assert AttentionDescriptor(lite.backbone, merge=False).out_dim == 1600
    with pytest.raises(ValueError, match="pooling='flat' is the paper's input of the random RNNs"):
        AttentionDescriptor(lite.backbone, pooling="flat")
    with pytest.raises(ValueError, match="pooling='flat' is the paper's input of the random RNNs"):
        descriptor_from_attention(torch.rand(1, 320, 7, 7), torch.rand(1, 320, 7, 7), None, "dam", pooling="flat")
    # the paper preset takes its own settings given explicitly, and refuses others
    paper = AttentionDescriptor("efficientnet_lite0", pretrained=False, preset="paper", num_rnn=16, pooling="flat")
    assert paper.recipe == AttentionDescriptor("efficientnet_lite0", pretrained=False, preset="paper").recipe
    with pytest.raises(ValueError, match=r"fixes the recipe and the tap; also given: \['num_rnn'\]"):
        AttentionDescriptor("efficientnet_lite0", pretrained=False, preset="paper", num_rnn=8)
    # a setting the preset leaves at the default is type-checked as a recipe's is
    with pytest.raises(TypeError, match="normalize must be True or False, got 1"):
        AttentionDescriptor("efficientnet_lite0", pretrained=False, preset="paper", normalize=1)
    # a setting given explicitly at the library's default, which the paper's differs from, is refused too
    for kw in ({"num_rnn": 0}, {"pooling": "regional"}, {"pool_scale": 10.0}):
        with pytest.raises(ValueError, match=f"also given: \\['{next(iter(kw))}'\\]"):
            AttentionDescriptor("efficientnet_lite0", pretrained=False, preset="paper", **kw)
    # the dtype follows the backbone without RNN weights, empty batches included
    d64 = AttentionDescriptor("efficientnet_lite0", pretrained=False).double()
    assert d64(torch.zeros(0, 3, 32, 32, dtype=torch.uint8)).dtype == torch.float64
    assert d64(images[:1]).dtype == torch.float64
    # normalize=False: every region is unit-norm already, 1 tap group (stage5) x 5 regions
    raw = AttentionDescriptor("efficientnet_lite0", pretrained=False, normalize=False)(images[:2])
    assert torch.allclose(raw.norm(dim=1), torch.full((2,), 5.0 ** 0.5), atol=1e-5)


def test_a_state_dict_of_the_other_encoding_names_num_rnn():
    # a descriptor with the paper's 16 RNNs and one without: neither state dict loads silently into the other
    old = AttentionDescriptor("efficientnet_lite0", pretrained=False, num_rnn=16)
    new = AttentionDescriptor("efficientnet_lite0", pretrained=False)
    with pytest.raises(RuntimeError, match=r"saved by a descriptor with num_rnn=16, .*build it with num_rnn=16"):
        new.load_state_dict(old.state_dict())
    with pytest.raises(RuntimeError, match=r"has 16 random RNNs .*saved by a descriptor with num_rnn=0"):
        old.load_state_dict(new.state_dict())
    assert new.load_state_dict(old.state_dict(), strict=False).unexpected_keys == ["pool.weights"]
    new.load_state_dict(AttentionDescriptor("efficientnet_lite0", pretrained=False, seed=3).state_dict())


def test_a_wrappers_state_dict_gets_torchs_own_message():
    # keys with another prefix (a wrapper's) are not this descriptor's: torch's key lists, not a num_rnn diagnosis
    rnns = AttentionDescriptor("efficientnet_lite0", pretrained=False, num_rnn=16)
    state = AttentionDescriptor("efficientnet_lite0", pretrained=False).state_dict()
    wrapped = {f"module.{k}": v for k, v in state.items()}
    with pytest.raises(RuntimeError, match="Missing key"):
        rnns.load_state_dict(wrapped)


def test_the_recipes_gem_exponent_is_the_regional_poolings():
    # L: 2 channels on a 2 x 2 map, G unused (fusion none). GeM with p = 3 by hand: the whole map
    # (mean x^3)^(1/3) per channel, each cell of the 2 x 2 grid its one value; each region L2-normalised.
    L = torch.tensor([[[1.0, 2.0], [3.0, 4.0]], [[2.0, 2.0], [2.0, 2.0]]])[None]
    whole = torch.tensor([((1 + 8 + 27 + 64) / 4) ** (1 / 3), 2.0])
    cells = L[0].flatten(1).T  # (4 cells row-major, 2 channels)
    ref = F.normalize(torch.cat([F.normalize(whole, dim=0)[None], F.normalize(cells, dim=1)]).flatten(), dim=0)
    net = nn.Sequential(nn.Conv2d(3, 2, 1), nn.AdaptiveAvgPool2d(2), nn.Flatten(), nn.Linear(8, 3))
    desc = AttentionDescriptor(net, tap="1", input_size=(8, 8), recipe=DescriptorRecipe(fusion="none", gem_p=3))
    assert torch.allclose(desc.from_attention(L, torch.zeros_like(L))[0], ref, atol=1e-6)
    assert torch.allclose(descriptor_from_attention(L, torch.zeros_like(L), None, "none", gem_p=3.0)[1][0], ref,
                          atol=1e-6)
    # p = 2 weighs the large values less: another whole-map direction
    p2 = descriptor_from_attention(L, torch.zeros_like(L), None, "none", gem_p=2.0)[1][0]
    whole2 = F.normalize(torch.tensor([((1 + 4 + 9 + 16) / 4) ** 0.5, 2.0]), dim=0)
    assert torch.allclose(p2[:2] * 5 ** 0.5, whole2, atol=1e-6) and not torch.allclose(p2, ref, atol=1e-3)


@pytest.mark.parametrize("gem_p", [0, -1.0, float("inf"), float("nan"), True, "3"])
def test_the_gem_exponent_must_be_a_positive_finite_number(gem_p):
    with pytest.raises(ValueError, match="gem_p must be a positive finite number"):
        DescriptorRecipe(gem_p=gem_p)
    with pytest.raises(ValueError, match="gem_p must be a positive finite number"):
        descriptor_from_attention(torch.rand(1, 4, 2, 2), torch.rand(1, 4, 2, 2), None, "none", gem_p=gem_p)


def test_the_gem_exponent_without_regional_pooling_is_refused():
    # the flat map has no GeM: an exponent other than the default would do nothing
    other = DescriptorRecipe.gem_p + 1.0
    with pytest.raises(ValueError, match=f"gem_p={other} sets the regional GeM pooling, and pooling='flat' has none"):
        DescriptorRecipe(pooling="flat", num_rnn=16, gem_p=other)
    assert DescriptorRecipe(pooling="flat", num_rnn=16, gem_p=DescriptorRecipe.gem_p).pooling == "flat"
