"""attnloop.pooling (regional GeM code), the joined stage6+stage7 tap, and the two presets' configuration."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from helpers import condition_head
from torch import nn

from attnloop import AttentionDescriptor
from attnloop.backbones import build_backbone, efficientnet_lite0
from attnloop.descriptor import DescriptorRecipe, descriptor_from_attention
from attnloop.fusion import fuse
from attnloop.guided_backprop import guided_backprop, softmax_seeded_gradient
from attnloop.pooling import fuse_groups, gem_regions, regional_code, regional_code_dim, unit_scale
from attnloop.rnn_pool import random_rnn_pool


def test_gem_regions_hand_computed():
    x = torch.tensor([[1.0, 2.0, 3.0, 4.0], [5.0, 6.0, 7.0, 8.0], [0.0, 0.0, -1.0, 0.0], [2.0, 2.0, 2.0, 2.0]])
    x = x[None, None]  # (1, 1, 4, 4)
    r = gem_regions(x, p=2.0, levels=(1, 2))
    assert r.shape == (1, 5, 1)
    floor = 1e-6 * 8.0  # relative to the map's max |x|
    vals = x.clamp_min(floor)
    assert r[0, 0, 0] == pytest.approx(float(vals.pow(2).mean().sqrt()))  # the whole map
    assert r[0, 1, 0] == pytest.approx(((1 + 4 + 25 + 36) / 4) ** 0.5)  # top-left cell
    assert r[0, 2, 0] == pytest.approx(((9 + 16 + 49 + 64) / 4) ** 0.5)  # top-right
    assert r[0, 4, 0] == pytest.approx(((2 * floor**2 + 4 + 4) / 4) ** 0.5, rel=1e-5)  # bottom-right: -1 -> floor
    # p = 1 is average pooling of the positive part; a large p tends to the max
    assert gem_regions(x.clamp_min(0), p=1.0, levels=(1,))[0, 0, 0] == pytest.approx(float(x.clamp_min(0).mean()),
                                                                                     rel=1e-5)
    assert gem_regions(x, p=30.0, levels=(1,))[0, 0, 0] == pytest.approx(8.0, rel=0.1)
    with pytest.raises(ValueError, match="levels"):
        gem_regions(x, levels=(0,))
    with pytest.raises(ValueError, match="p must be positive"):
        gem_regions(x, p=0.0)


def test_gem_is_scale_equivariant_and_the_code_scale_invariant():
    # The floor is relative to each sample's max |x|: a map of tiny magnitude (random weights give
    # stage6 activations of ~1e-7) pools exactly like the same map at unit scale.
    g = torch.Generator().manual_seed(2)
    x = torch.randn(2, 6, 5, 7, generator=g)
    x[1] *= 3.0  # the two samples at different scales
    r = gem_regions(x, 2.0, (1, 2))
    for k in (1e-9, 1e-3, 1e4):
        assert torch.allclose(gem_regions(k * x, 2.0, (1, 2)), k * r, rtol=1e-5, atol=0)
        assert torch.allclose(regional_code(k * x, (2, 4)), regional_code(x, (2, 4)), atol=1e-6)
    # an absolute floor of 1e-6 would have made every sample of 1e-8 x one constant code
    tiny = regional_code(1e-8 * x, (2, 4))
    assert float((tiny[0] - tiny[1]).abs().max()) > 0.05
    # an all-zero sample pools to zeros, GeM and code alike (no evidence), never NaN
    zero = torch.zeros(1, 6, 5, 7)
    assert torch.equal(gem_regions(zero), torch.zeros(1, 5, 6))
    assert torch.equal(regional_code(zero, (2, 4)), torch.zeros(1, 30))
    assert gem_regions(x[:0]).shape == (0, 5, 6)


def test_random_weight_descriptors_tell_images_apart():
    # Plumbing with pretrained=False must still see the image: each mode's descriptors of three
    # different photographs differ, and one image twice gives one descriptor.
    skdata = pytest.importorskip("skimage.data")
    photos = [skdata.astronaut(), skdata.chelsea(), skdata.coffee()]
    images = torch.stack([F.interpolate(torch.from_numpy(p).permute(2, 0, 1)[None].float(), size=(120, 160),
                                        mode="area")[0].round().to(torch.uint8) for p in photos])
    for kw in ({}, {"preset": "paper"}):
        d = AttentionDescriptor("efficientnet_lite0", pretrained=False, **kw)
        parts = d.parts(torch.cat([images, images[:1]]))
        assert float(parts.tap.abs().max()) < 1e-4  # the regime of the defect: tiny random-weight features
        for mode in ("none", "dam", "eam", "gaf", "ega"):
            e = d.from_attention(parts.tap, parts.grad, mode)
            cos = e @ e.T
            assert float(cos[0, 3]) == pytest.approx(1.0, abs=1e-6), (kw, mode)
            off = cos[:3, :3][~torch.eye(3, dtype=torch.bool)]
            # one constant code (the defect) gives 1; random stage5 features are alike, up to 0.993 here
            assert float(off.max()) < 0.995, (kw, mode, cos)


def test_regional_code_groups_are_unit_blocks():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(3, 12, 5, 6, generator=g)
    code = regional_code(x, groups=(4, 8), p=3.0, levels=(1, 2))
    assert code.shape == (3, regional_code_dim((4, 8), (1, 2))) == (3, 60)
    blocks = torch.cat([code[:, :20].reshape(3, 5, 4), code[:, 20:].reshape(3, 5, 8)], dim=2)
    norms = torch.cat([blocks[..., :4].norm(dim=2), blocks[..., 4:].norm(dim=2)], dim=1)
    assert torch.allclose(norms, torch.ones(3, 10), atol=1e-6)  # one unit vector per (group, region)
    ref = F.normalize(gem_regions(x[:, 4:], 3.0, (1, 2)), dim=2).flatten(1)
    assert torch.allclose(code[:, 20:], ref)
    # a translation by whole cells leaves the global region unchanged (the flat map would change entirely)
    rolled = torch.roll(x, shifts=3, dims=3)
    assert torch.allclose(gem_regions(rolled, 3.0, (1,)), gem_regions(x, 3.0, (1,)), atol=1e-5)
    assert regional_code(x[:0], groups=(4, 8)).shape == (0, 60)
    with pytest.raises(ValueError, match="summing to the 12 channels"):
        regional_code(x, groups=(4, 4))


def test_fuse_groups_is_fusion_per_group():
    g = torch.Generator().manual_seed(1)
    L, G = torch.randn(2, 10, 3, 3, generator=g), torch.randn(2, 10, 3, 3, generator=g)
    for mode in ("dam", "gaf"):
        got = fuse_groups(L, G, mode, (4, 6))
        want = torch.cat([fuse(L[:, :4], unit_scale(G[:, :4]), mode), fuse(L[:, 4:], unit_scale(G[:, 4:]), mode)], 1)
        assert torch.allclose(got, want)
        assert not torch.allclose(got, fuse(L, unit_scale(G), mode))  # joint normalisation differs


def test_joined_tap_equals_the_separate_taps():
    kw = {"pretrained": False, "seed": 3, "input_size": (96, 128)}
    joined = condition_head(efficientnet_lite0(tap="stage6+stage7", **kw))
    s6 = condition_head(efficientnet_lite0(tap="stage6", **kw))
    s7 = condition_head(efficientnet_lite0(tap="stage7", **kw))  # G by the closed form
    assert joined.tap_shape == (512, 3, 4) and joined.tap_groups == (192, 320)
    x = torch.randint(0, 256, (2, 3, 60, 80), dtype=torch.uint8)
    L, G = guided_backprop(joined, x)
    L6, G6 = guided_backprop(s6, x)
    L7, G7 = guided_backprop(s7, x)
    assert torch.equal(L[:, :192], L6) and torch.allclose(L[:, 192:], L7, atol=1e-6)
    assert torch.allclose(G[:, :192], G6, rtol=1e-5, atol=1e-12 * float(G6.abs().max()))
    assert torch.allclose(G[:, 192:], G7, rtol=1e-6, atol=2e-6 * float(G7.abs().max()))  # G7: the closed form
    with torch.no_grad():
        assert torch.allclose(joined(x), s7(x), atol=1e-5)  # the classifier is unchanged
    with pytest.raises(ValueError, match="different resolutions"):
        efficientnet_lite0(pretrained=False, tap="stage5+stage7")
    with pytest.raises(ValueError, match="unknown EfficientNet-Lite tap"):
        efficientnet_lite0(pretrained=False, tap="stage7+head")


@pytest.mark.parametrize("tap", ["stage6+stage7", "stage4+stage5"])
def test_joined_tap_runs_each_block_once_with_the_two_call_gradients(tap):
    # forward_split (the descriptor's no-autograd path) records the blocks between the joined stages once
    # and replays their backward; it must give the gradients of forward_from_tap(forward_to_tap(x)).
    net = efficientnet_lite0(tap=tap, pretrained=False, seed=5, input_size=(96, 128))
    calls = [0] * len(net._blocks)
    hooks = [b.register_forward_hook(lambda *a, k=k: calls.__setitem__(k, calls[k] + 1))
             for k, b in enumerate(net._blocks)]
    x = torch.randint(0, 256, (2, 3, 60, 80), dtype=torch.uint8)
    L, G = guided_backprop(net, x)
    assert calls == [1] * len(net._blocks)
    for h in hooks:
        h.remove()
    with torch.no_grad():
        tap_ref = net.forward_to_tap(net.preprocess(x))
    G_ref = softmax_seeded_gradient(tap_ref, net.forward_from_tap, guided=False)
    assert torch.equal(L, tap_ref)
    assert torch.allclose(G, G_ref, rtol=1e-6, atol=1e-9 * float(G_ref.abs().max()))
    assert float(G[:, : net.tap_groups[0]].abs().max()) > 0  # the first stage gets the replayed gradient
    # the differentiable path keeps the two calls (and the same values)
    xf = x.float() / 255
    _, G1 = guided_backprop(net, xf)
    _, G2 = guided_backprop(net.requires_grad_(True), xf, create_graph=True)
    assert G2.requires_grad
    assert torch.allclose(G2.detach(), G1, rtol=1e-5, atol=1e-6 * float(G1.abs().max()))


def test_fuse_groups_passes_the_groups_not_attended_unfused():
    g = torch.Generator().manual_seed(2)
    L, G = torch.randn(2, 10, 3, 3, generator=g), torch.randn(2, 10, 3, 3, generator=g)
    for mode in ("dam", "ega"):
        got = fuse_groups(L, G, mode, (4, 6), (False, True))
        assert torch.equal(got[:, :4], L[:, :4])
        assert torch.equal(got[:, 4:], fuse(L[:, 4:], unit_scale(G[:, 4:]), mode))
        assert torch.equal(fuse_groups(L, G, mode, (4, 6), (True, True)), fuse_groups(L, G, mode, (4, 6)))
    assert torch.equal(fuse_groups(L, G, "dam", None, (False,)), L)
    with pytest.raises(ValueError, match="2 flags for 1 groups"):
        fuse_groups(L, G, "dam", None, (True, False))


@pytest.mark.parametrize("tap,attend,closed", [("stage6+stage7", "stage7", True), ("stage6+stage7", "stage7", False),
                                              ("stage6+stage7", "stage6", False), ("stage4+stage5", "stage5", False),
                                              ("stage4+stage5", "stage4", False)])
def test_attend_computes_G_at_the_named_stages_only(tap, attend, closed):
    # closed: EfficientNet's closed form (G at the last stage); otherwise the one-pass autograd path
    # (forward_split; with the closed form switched off where it would apply).
    kw = {"pretrained": False, "seed": 5, "input_size": (96, 128)}
    both = condition_head(efficientnet_lite0(tap=tap, **kw))
    net = condition_head(efficientnet_lite0(tap=tap, attend=attend, **kw))
    second = tap.split("+")[1]
    assert net.attend == attend and net.attended_groups == ((False, True) if attend == second else (True, False))
    if not closed:
        net.tap_and_seeded_gradient = lambda x: None
    x = torch.randint(0, 256, (2, 3, 60, 80), dtype=torch.uint8)
    assert (net.tap_and_seeded_gradient(net.preprocess(x)) is not None) == closed
    calls = [0] * len(net._blocks)
    hooks = [b.register_forward_hook(lambda *a, k=k: calls.__setitem__(k, calls[k] + 1))
             for k, b in enumerate(net._blocks)]
    L, G = guided_backprop(net, x)
    assert calls == [1] * len(net._blocks)  # each block once, on the way to the logits
    for h in hooks:
        h.remove()
    L_ref, G_ref = guided_backprop(both, x)  # every stage attended: autograd
    c = net.tap_groups[0]
    on = slice(c, None) if attend == second else slice(0, c)
    off = slice(0, c) if attend == second else slice(c, None)
    assert torch.equal(L, L_ref)
    assert float(G[:, off].abs().max()) == 0.0
    assert float(G[:, on].abs().max()) > 0
    tol = 2e-6 if closed else 1e-9  # the closed form sums in another order (float32)
    assert torch.allclose(G[:, on], G_ref[:, on], rtol=1e-6, atol=tol * float(G_ref[:, on].abs().max()))
    # the two-call path (the differentiable one) gives the same
    with torch.no_grad():
        tap_ref = net.forward_to_tap(net.preprocess(x))
    assert torch.allclose(softmax_seeded_gradient(tap_ref, net.forward_from_tap, guided=False), G,
                          rtol=1e-6, atol=tol * float(G.abs().max()))
    with torch.no_grad():
        assert torch.equal(net(x), both(x))  # the classifier is unchanged


def test_attend_names_stages_of_the_tap():
    with pytest.raises(ValueError, match="must name stages of the tap"):
        efficientnet_lite0(pretrained=False, tap="stage6+stage7", attend="stage5")
    with pytest.raises(ValueError, match="must name stages of the tap"):
        efficientnet_lite0(pretrained=False, tap="stage7", attend="")
    assert efficientnet_lite0(pretrained=False, tap="stage7", attend="stage7").attended_groups == (True,)
    assert efficientnet_lite0(pretrained=False, tap="stage7+stage6").attend == "stage6+stage7"
    assert efficientnet_lite0(pretrained=False, tap="stage6+stage7", attend=["stage7"]).attend == "stage7"
    with pytest.raises(ValueError, match="must name stages of the tap"):
        efficientnet_lite0(pretrained=False, tap="stage6+stage7", attend=[])
    assert build_backbone("vgg16", pretrained=False, attend="pool5").tap == "pool5"  # its one layer, attended
    with pytest.raises(ValueError, match="VGG16's tap is one layer"):
        build_backbone("vgg16", pretrained=False, attend="pool4")


@pytest.mark.parametrize("attended", [(True, False, True), (False, True, False), (False, False, True),
                                      (True, True, False), (True, False, False)])
def test_attend_on_a_three_stage_tap(attended):
    # No Lite0 tap joins three stages of one resolution, but the code is generic: join the outputs of the
    # last two stage6 blocks and stage7 (blocks 13, 14, 15, all 7 x 9) and check every pattern, a middle
    # stage not attended included, against G with every stage attended (zeroed where not attended).
    def joined(flags):
        net = condition_head(efficientnet_lite0(pretrained=False, seed=2, tap="stage6+stage7",
                                               input_size=(96, 128)))
        net.tap_groups, net._group_blocks = (192, 192, 320), (13, 14, 15)
        net.tap_shape = (704, 3, 4)
        net.attended_groups, net._first_attended = flags, flags.index(True)
        return net

    x = torch.randint(0, 256, (2, 3, 60, 80), dtype=torch.uint8)
    L_all, G_all = guided_backprop(joined((True, True, True)), x)
    net = joined(attended)
    L, G = guided_backprop(net, x)  # the one-pass path (forward_split), or the closed form for the last stage alone
    with torch.no_grad():
        tap = net.forward_to_tap(net.preprocess(x))
    G_two_calls = softmax_seeded_gradient(tap, net.forward_from_tap, guided=False)
    mask = torch.cat([torch.full((c,), float(a)) for c, a in zip(net.tap_groups, attended)])[None, :, None, None]
    assert torch.equal(L, L_all) and torch.equal(L, tap)
    # the last stage alone is the closed form's case (float32 rounding apart), the others autograd's
    scale = (2e-6 if attended == (False, False, True) else 1e-9) * float(G_all.abs().max())
    assert torch.allclose(G, G_all * mask, rtol=1e-6, atol=scale)
    assert torch.allclose(G_two_calls, G_all * mask, rtol=1e-6, atol=scale)
    assert all((float(g.abs().max()) > 0) == a for g, a in zip(G.split(net.tap_groups, 1), attended))


def test_descriptor_attend_argument():
    both = AttentionDescriptor("efficientnet_lite0", fusion="dam", pretrained=False, tap="stage6+stage7",
                               attend="stage6+stage7")
    assert both.backbone.tap == "stage6+stage7" and both.attended_groups == (True, True)
    last = AttentionDescriptor("efficientnet_lite0", fusion="dam", pretrained=False, tap="stage6+stage7",
                               attend="stage7")
    assert last.attended_groups == (False, True)
    x = torch.randint(0, 256, (1, 3, 60, 80), dtype=torch.uint8)
    a, b = both.parts(x), last.parts(x)
    assert torch.equal(a.tap, b.tap) and not torch.allclose(a.descriptor, b.descriptor)
    assert torch.allclose(a.descriptor, descriptor_from_attention(a.tap, a.grad, None, "dam",
                                                                  groups=(192, 320))[1], atol=1e-6)
    explicit = AttentionDescriptor("efficientnet_lite0", pretrained=False, tap="stage4+stage5", attend="stage5")
    assert explicit.attended_groups == (False, True)
    with pytest.raises(ValueError, match="fixes the recipe and the tap; also given: \\['attend'\\]"):
        AttentionDescriptor("efficientnet_lite0", pretrained=False, preset="paper", attend="stage7")
    with pytest.raises(ValueError, match="attend= applies to a backbone name"):
        AttentionDescriptor(last.backbone, attend="stage7")
    with pytest.raises(ValueError, match="must name stages of the tap"):  # the default's tap is stage5
        AttentionDescriptor("efficientnet_lite0", pretrained=False, attend="stage7")


def test_default_configuration():
    d = AttentionDescriptor("efficientnet_lite0", fusion="dam", pretrained=False)
    # stage5 (112 channels, stride 16) of a 256 x 320 input: one tap group, attended
    assert d.backbone.tap == "stage5" and d.backbone.input_size == (256, 320)
    assert d.backbone.tap_shape == (112, 16, 20) and d.tap_groups == (112,) and d.attended_groups == (True,)
    r = d.recipe
    # no RNNs: the regional code (GeM p = 3), L2-normalised, is the descriptor
    assert (r.pooling, r.num_rnn, r.merges, r.gem_p) == ("regional", 0, False, 3.0)
    assert d.pool is None and d.out_dim == 5 * 112
    x = torch.randint(0, 256, (2, 3, 120, 160), dtype=torch.uint8)
    parts = d.parts(x)
    code = regional_code(fuse(parts.tap, unit_scale(parts.grad), "dam"), None, 3.0, (1, 2))
    assert torch.allclose(parts.descriptor, F.normalize(code, dim=1), atol=1e-6)
    assert torch.allclose(d.from_attention(parts.tap, parts.grad, "gaf"),
                          descriptor_from_attention(parts.tap, parts.grad, None, "gaf", gem_p=3.0)[1])
    assert d(x[:0]).shape == (0, 560)
    # num_rnn=16: the paper's RNNs on that code, input at norm 10
    rnns = AttentionDescriptor("efficientnet_lite0", fusion="dam", pretrained=False, num_rnn=16)
    assert rnns.pool.weights.shape == (16, 64, 560) and rnns.out_dim == 1024
    ref = F.normalize(random_rnn_pool(10.0 * F.normalize(code, dim=1)[:, :, None, None], rnns.pool.weights,
                                      merge=False), dim=1)
    assert torch.allclose(rnns.from_attention(parts.tap, parts.grad), ref, atol=1e-6)
    explicit = AttentionDescriptor("efficientnet_lite0", pretrained=False, tap="stage7")
    assert explicit.backbone.tap_shape == (320, 7, 7)  # an explicit tap: the backbone's own 224 x 224


@pytest.mark.parametrize("backbone, tap_shape, rnn_in", [("efficientnet_lite0", (320, 7, 7), 160 * 49),
                                                         ("vgg16", (512, 7, 7), 256 * 49)])
def test_paper_preset_configuration(backbone, tap_shape, rnn_in):
    d = AttentionDescriptor(backbone, fusion="gaf", pretrained=False, preset="paper")
    assert d.backbone.tap_shape == tap_shape and d.backbone.input_size == (224, 224)
    r = d.recipe
    got = (r.fusion, r.pooling, r.pool_scale, r.merges, r.num_rnn, r.out_features)
    assert got == ("gaf", "flat", None, True, 16, 64)
    assert d.pool.weights.shape == (16, 64, rnn_in)  # VGG16: the paper's 16 RNNs of 64 x 12544
    if backbone == "efficientnet_lite0":
        x = torch.randint(0, 256, (1, 3, 90, 120), dtype=torch.uint8)
        parts = d.parts(x)
        ref = F.normalize(random_rnn_pool(fuse(parts.tap, unit_scale(parts.grad), "gaf"), d.pool.weights), dim=1)
        assert torch.allclose(parts.descriptor, ref, atol=1e-6)  # raw fused map, merged, flat
    with pytest.raises(ValueError, match="fixes the recipe"):
        AttentionDescriptor(backbone, pretrained=False, preset="paper", pool_scale=5.0)
    with pytest.raises(ValueError, match="fixes the recipe"):
        AttentionDescriptor(backbone, pretrained=False, preset="paper", tap="pool4")
    with pytest.raises(ValueError, match="unknown preset"):
        AttentionDescriptor(backbone, pretrained=False, preset="ours")


def test_recipe_checks():
    with pytest.raises(ValueError, match="unknown pooling"):
        DescriptorRecipe(pooling="max")
    assert DescriptorRecipe(pooling="flat", num_rnn=16).merges and not DescriptorRecipe(num_rnn=16).merges
    assert DescriptorRecipe(merge=True, num_rnn=16).merges
    assert not DescriptorRecipe(merge=False).merges  # no RNNs: nothing to merge
    with pytest.raises(ValueError, match="merge set the random RNNs"):
        DescriptorRecipe(merge=True)


def test_an_empty_region_codes_to_zeros_not_to_the_uniform_vector():
    # An all-zero map (DAM's or GAF's where G is flat: a saturated softmax) pools to the floor in every
    # channel; normalised, that would be one uniform vector for every such image (cosine 1 between any two).
    assert torch.equal(regional_code(torch.zeros(2, 4, 3, 3)), torch.zeros(2, 20))
    # one empty cell (top-left of a 2 x 2 grid on 4 x 4; negative values are below the floor too): its slot
    # is zero, every other region a unit vector
    x = torch.rand(1, 3, 4, 4) + 0.5
    x[:, :, :2, :2] = -torch.rand(1, 3, 2, 2)
    regions = regional_code(x).view(5, 3)
    assert torch.equal(regions[1], torch.zeros(3))
    assert torch.allclose(regions[[0, 2, 3, 4]].norm(dim=1), torch.ones(4))
    assert torch.allclose(regions[2], F.normalize(gem_regions(x)[0, 2], dim=0))


def test_a_saturated_classifier_gives_no_match_rather_than_every_match():
    # G is exactly zero when the softmax is one-hot: DAM/GAF fuse to zeros, and two unrelated images must not
    # get the same descriptor (they did: cosine 1.0); `none` and EAM keep L and still tell them apart
    torch.manual_seed(0)
    net = nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2), nn.Flatten(),
                        nn.Linear(8 * 16 * 16, 10))
    with torch.no_grad():
        net[4].weight.mul_(1e4)
    ramp = torch.linspace(0, 1, 64)
    images = torch.stack([ramp.view(1, 1, 64).expand(3, 64, 64), torch.rand(3, 64, 64) ** 4])
    for fusion in ("dam", "gaf", "none"):
        L, G, fused, desc = AttentionDescriptor(net, tap="2", input_size=(32, 32), fusion=fusion).parts(images)
        assert bool((G == 0).all())
        if fusion == "none":
            assert 0.5 < float(desc[0] @ desc[1]) < 0.99
        else:
            assert torch.equal(desc, torch.zeros_like(desc))  # no evidence: cosine 0 with every frame
