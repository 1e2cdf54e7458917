"""benchmarks/attention_hypotheses.py: its baseline is the library's default, its variants are what they say."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from attnloop import AttentionDescriptor
from attnloop.fusion import FUSION_MODES
from attnloop.pooling import fuse_groups, regional_code


@pytest.fixture(scope="module")
def hyp(load_script):
    return load_script("benchmarks/attention_hypotheses.py")


@pytest.fixture(scope="module")
def maps():
    g = torch.Generator().manual_seed(4)
    return torch.randn(2, 512, 7, 9, generator=g), torch.randn(2, 512, 7, 9, generator=g) * 1e-5


@pytest.mark.parametrize("mode", FUSION_MODES)
def test_the_sweeps_baseline_is_the_library_default(hyp, maps, mode):
    # the "paper N, own S" rows must be the default descriptor's numbers, or the sweep compares to nothing
    L, G = maps
    assert hyp.ATTENDED == (False, True)
    assert torch.allclose(hyp.fused(L, G, mode), fuse_groups(L, G, mode, (192, 320), hyp.ATTENDED))
    desc = AttentionDescriptor("efficientnet_lite0", fusion=mode, pretrained=False)
    assert torch.allclose(hyp.descriptor(hyp.fused(L, G, mode), None), desc.from_attention(L, G), atol=1e-6)
    # sessions 1-5 measured with the paper's 16 RNNs on the regional code (seed 0 here)
    rnns = AttentionDescriptor("efficientnet_lite0", fusion=mode, pretrained=False, num_rnn=16)
    assert torch.allclose(hyp.descriptor(hyp.fused(L, G, mode), 0), rnns.from_attention(L, G), atol=1e-6)


def test_rank_normalize_hand_computed(hyp):
    g = torch.tensor([[[[3.0, -1.0], [10.0, 0.5]]]])  # (1, 1, 2, 2): ranks 2, 0, 3, 1 of 4
    assert torch.equal(hyp.rank_normalize(g, (1, 2, 3)), torch.tensor([[[[2 / 3, 0.0], [1.0, 1 / 3]]]]))
    two = torch.stack([g[0], -g[0]], 1)  # (1, 2, 2, 2): per channel over (H, W)
    r = hyp.rank_normalize(two, (2, 3))
    assert torch.equal(r[:, 0], torch.tensor([[[2 / 3, 0.0], [1.0, 1 / 3]]]))
    assert torch.equal(r[:, 1], torch.tensor([[[1 / 3, 1.0], [0.0, 2 / 3]]]))


def test_seeds(hyp):
    z = torch.tensor([[4.0, 3.0, 2.0, 1.0, 0.0, -1.0, -2.0]])
    p = z.softmax(1)
    assert torch.equal(hyp._seed(p, z, "own"), p)
    top5 = hyp._seed(p, z, "top5")
    assert torch.allclose(top5[0, :5], p[0, :5] / p[0, :5].sum()) and torch.equal(top5[0, 5:], torch.zeros(2))
    assert torch.allclose(hyp._seed(p, z, "top5-uniform"), torch.tensor([[0.2] * 5 + [0.0] * 2]))
    assert torch.allclose(hyp._seed(p, z, "T2"), (z / 2).softmax(1))
    h = hyp._seed(p, z, "entropy")
    assert torch.allclose(h, -p * p.log() / (-p * p.log()).sum()) and torch.allclose(h.sum(), torch.tensor(1.0))


def test_per_channel_and_sign_variants(hyp):
    L = torch.ones(1, 2, 1, 3)
    G = torch.tensor([[[[0.0, 1.0, 2.0]], [[-4.0, 0.0, 4.0]]]])
    # per channel over (H, W): each channel spans [0, 1] on its own
    assert torch.allclose(hyp.attention_map(G, "dam", "channel"), torch.tensor([[[[0.0, 0.5, 1.0]], [[0.0, 0.5, 1.0]]]]))
    # over (C, H, W) (the paper): one range for both channels, [-4, 4]
    assert torch.allclose(hyp.attention_map(G, "dam", "global"), torch.tensor([[[[0.5, 0.625, 0.75]], [[0.0, 0.5, 1.0]]]]))
    a = hyp.fused(torch.ones(1, 512, 1, 3), torch.cat([G[:, :1]] * 192 + [G[:, 1:]] * 320, 1), "dam", sign=True)
    assert torch.allclose(a[0, 200, 0], torch.tensor([1.0, 0.0, 1.0]))  # |G| of the second block: 4, 0, 4
    assert hyp.fused(L, G, "none") is L


# ------------------------------------------------------------------ session 3: taps, G's form, layouts
def test_default_layout_is_the_librarys_regional_code(hyp):
    g = torch.Generator().manual_seed(1)
    x = torch.randn(3, 512, 7, 9, generator=g)
    ref = regional_code(x, (192, 320))
    assert torch.allclose(hyp.layout_code(list(x.split((192, 320), 1))), ref, atol=1e-6)
    # a map at another resolution (stage5's 14 x 18) is pooled on its own cells
    y = torch.randn(3, 112, 14, 18, generator=g)
    assert torch.allclose(hyp.layout_code([y]), regional_code(y), atol=1e-6)


def test_layouts_hand_computed(hyp):
    # R-MAC's rule on a 7 x 9 map: level 1 two 7 x 7 squares at x = 0 and 2, level 2 six 4 x 4 at x = 0, 2, 5
    # and y = 0, 3, level 3 twelve 3 x 3 (x = 0, 2, 4, 6; y = 0, 2, 4)
    boxes = hyp._rmac_boxes(7, 9)
    assert boxes[:2] == [(0, 7, 0, 7), (0, 7, 2, 9)]
    assert boxes[2:8] == [(y, y + 4, x, x + 4) for y in (0, 3) for x in (0, 2, 5)]
    assert boxes[8:] == [(y, y + 3, x, x + 3) for y in (0, 2, 4) for x in (0, 2, 4, 6)]
    strips, agg = hyp.LAYOUTS["whole + 3 strips"]
    assert strips(7, 9) == [(0, 7, 0, 9), (0, 3, 0, 9), (2, 5, 0, 9), (4, 7, 0, 9)] and agg == "concat"
    # strips are invariant to a horizontal circular shift of the map; the 2 x 2 grid is not
    x = torch.rand(1, 8, 7, 9, generator=torch.Generator().manual_seed(2))
    rolled = x.roll(4, dims=3)
    assert torch.allclose(hyp.layout_code([x], "3 strips"), hyp.layout_code([rolled], "3 strips"), atol=1e-6)
    assert not torch.allclose(hyp.layout_code([x]), hyp.layout_code([rolled]), atol=1e-3)
    # summed: one unit vector per map
    assert torch.allclose(hyp.layout_code([x], "R-MAC regions summed").norm(dim=1), torch.ones(1))


def test_spatial_share_hand_computed(hyp):
    flat = torch.arange(4.0).view(1, 4, 1, 1).expand(1, 4, 3, 3)  # each channel constant: no spatial part
    assert float(hyp.spatial_share(flat)) == 0.0
    same_mean = torch.tensor([[[[1.0, -1.0]], [[2.0, -2.0]]]])  # channel means 0: all of it spatial
    assert float(hyp.spatial_share(same_mean)) == 1.0
    # channels [0, 2] and [4, 4]: within = (1 + 0) / 2 = 0.5, total var of (0, 2, 4, 4) = 2.75
    mixed = torch.tensor([[[[0.0, 2.0]], [[4.0, 4.0]]]])
    assert abs(float(hyp.spatial_share(mixed)) - 0.5 / 2.75) < 1e-6


def test_crops(hyp):
    im = np.arange(2 * 8 * 3, dtype=np.uint8).reshape(2, 8, 3)
    assert hyp.crop(im, "full") is im
    assert np.array_equal(hyp.crop(im, "left"), im[:, :6]) and np.array_equal(hyp.crop(im, "right"), im[:, 2:])


def test_extract_taps_matches_the_library_and_the_clamp_by_hand(hyp):
    from attnloop.backbones.efficientnet_lite import efficientnet_lite
    from attnloop.guided_backprop import guided_backprop

    net = efficientnet_lite("lite0", pretrained=False, tap="stage7", input_size=hyp.SIZE, seed=3)
    images = [np.random.default_rng(i).integers(0, 256, (60, 80, 3), dtype=np.uint8) for i in range(2)]
    f = hyp.extract_taps(images, net=net)
    joined = efficientnet_lite("lite0", pretrained=False, tap="stage6+stage7", input_size=hyp.SIZE, seed=3)
    L, G = guided_backprop(joined, torch.stack([torch.from_numpy(im).permute(2, 0, 1) for im in images]))
    assert torch.allclose(torch.cat([f["L:stage6"], f["L:stage7"]], 1), L, atol=1e-6)
    assert torch.allclose(torch.cat([f["G:stage6"], f["G:stage7"]], 1), G, rtol=1e-4, atol=1e-12)
    # at stage7 only a 1x1 conv, batch-norm and ReLU6 lie before the global average pool: by hand,
    # dS/dhead = W_fc^T (S (S - |S|^2)) / HW on every position, clamped at 0, masked by 0 < pre < 6
    with torch.no_grad():
        L7 = f["L:stage7"]
        pre = net._bn1(net._conv_head(L7))
        p = f["logits"].softmax(1)
        seed = p * (p - (p * p).sum(1, keepdim=True))
        g_head = (seed @ net._fc.weight) / (L7.shape[2] * L7.shape[3])  # (B, 1280)
        scale = net._bn1.weight / (net._bn1.running_var + net._bn1.eps).sqrt()
        inner = ((pre > 0) & (pre < 6)) * (g_head.clamp(min=0) * scale)[:, :, None, None]
        gc7 = torch.einsum("bkhw,kc->bchw", inner, net._conv_head.weight[:, :, 0, 0])
    assert torch.allclose(f["Gc:stage7"], gc7, rtol=1e-4, atol=1e-3 * float(gc7.abs().max()))
    assert torch.equal(f["share:head"], torch.zeros(2))  # dS/d(head output) is constant over (H, W)
    assert (f["share:stage7"] > 0).all()


def test_block_macs(hyp):
    total, above = hyp.block_macs()
    h, w = 7, 9  # stage7 -> logits: the 1x1 head conv (320 -> 1280 on 7 x 9) and the classifier
    assert above["stage7"] == 320 * 1280 * h * w + 1280 * 1000
    assert above["stage7"] < above["stage6"] < above["stage5"] < above["stage4"] < total


def test_local_gradients_hand_computed(hyp):
    # each position's own softmax S(h, w) of z(h, w) = W_fc head(h, w) + b seeds the backward:
    # at stage7 dPhi/dhead(h, w) = W_fc^T (S (S - |S|^2))(h, w), then the ReLU6 mask, batch-norm scale, 1x1 conv
    from attnloop.backbones.efficientnet_lite import efficientnet_lite

    net = efficientnet_lite("lite0", pretrained=False, tap="stage7", input_size=hyp.SIZE, seed=5)
    l6 = torch.randn(2, 192, 7, 9, generator=torch.Generator().manual_seed(6))
    g = hyp.local_gradients(net, l6, "all")
    with torch.no_grad():
        L7 = net._blocks[-1](l6)
        pre = net._bn1(net._conv_head(L7))
        head = torch.nn.functional.relu6(pre)
        z = torch.einsum("nchw,kc->nkhw", head, net._fc.weight) + net._fc.bias[:, None, None]
        p = z.softmax(1)
        seed = p * (p - (p * p).sum(1, keepdim=True))
        g_head = torch.einsum("nkhw,kc->nchw", seed, net._fc.weight)
        scale = net._bn1.weight / (net._bn1.running_var + net._bn1.eps).sqrt()
        inner = ((pre > 0) & (pre < 6)) * g_head * scale[:, None, None]
        g7 = torch.einsum("nkhw,kc->nchw", inner, net._conv_head.weight[:, :, 0, 0])
    assert torch.allclose(g["stage7"], g7, rtol=1e-4, atol=1e-4 * float(g7.abs().max()))
    # the per-position logits average to the network's: the same classifier
    assert torch.allclose(z.mean((2, 3)), g["logits"], atol=1e-4)
    assert torch.equal(g["local_top1"], p.argmax(1))
    # a softmax over all 1000 classes picked as the top-1000 is the same softmax in another order
    top = hyp.local_gradients(net, l6, "top", 1000)
    for t in ("stage6", "stage7"):
        assert torch.allclose(top[t], g[t], rtol=1e-3, atol=1e-4 * float(g[t].abs().max()))
    # the seed is per position, so G is not the library's (one softmax of the pooled logits)
    glob = hyp.local_gradients(net, l6, "global")
    assert not torch.allclose(glob["stage7"] / glob["stage7"].abs().max(), g7 / g7.abs().max(), atol=0.05)


def test_local_gradients_global_is_the_librarys_g(hyp):
    from attnloop.backbones.efficientnet_lite import efficientnet_lite
    from attnloop.guided_backprop import guided_backprop

    images = [np.random.default_rng(i).integers(0, 256, (60, 80, 3), dtype=np.uint8) for i in range(2)]
    joined = efficientnet_lite("lite0", pretrained=False, tap="stage6+stage7", input_size=hyp.SIZE, seed=3)
    L, G = guided_backprop(joined, torch.stack([torch.from_numpy(im).permute(2, 0, 1) for im in images]))
    g = hyp.local_gradients(joined, L[:, :192], "global")
    assert torch.allclose(torch.cat([g["stage6"], g["stage7"]], 1), G, rtol=1e-4, atol=1e-6 * float(G.abs().max()))
    # a class subset: only those classes' rows of the classifier enter each position's softmax
    sub = hyp.local_gradients(joined, L[:, :192], "subset", 3, torch.tensor([7, 2, 900]))
    assert set(sub["local_top1"].unique().tolist()) <= {7, 2, 900}


def test_local_subset_and_macs(hyp):
    logits = torch.tensor([[5.0, 4.0, 3.0, 0.0, -1.0], [0.0, 4.0, 5.0, 3.0, -1.0]])
    # top-2 of each frame: {0, 1} and {2, 1}: class 1 twice, then 0 and 2 once (ties to the lower index)
    assert hyp.local_subset(logits, size=3, top=2).tolist() == [1, 0, 2]
    assert hyp.local_macs(5) == 2 * 1280 * 5 * 63
    assert hyp.local_macs(1000) == 2 * 1280 * 1000 * 63 - 2 * 1280 * 1000


def test_local_gradients_equal_weights(hyp):
    # every position's logit seed at unit norm: G is the sum over positions of dz(h, w)/dL^T u(h, w)
    from attnloop.backbones.efficientnet_lite import efficientnet_lite

    net = efficientnet_lite("lite0", pretrained=False, tap="stage7", input_size=hyp.SIZE, seed=5)
    l6 = torch.randn(1, 192, 7, 9, generator=torch.Generator().manual_seed(7))
    g = hyp.local_gradients(net, l6, "all")
    eq = hyp.local_gradients(net, l6, "all-equal")
    with torch.no_grad():
        head = net._head_features(net._blocks[-1](l6))
        p = (torch.einsum("nchw,kc->nkhw", head, net._fc.weight) + net._fc.bias[:, None, None]).softmax(1)
        norm = (p * (p - (p * p).sum(1, keepdim=True))).norm(dim=1)  # (1, 7, 9): each position's seed norm
    # at stage7 the path from one position's logits to L is that position's alone: G_eq(h, w) = G(h, w) / norm
    tol = 1e-4 * float(eq["stage7"].abs().max())
    assert torch.allclose(eq["stage7"], g["stage7"] / norm[:, None], rtol=1e-3, atol=tol)
    assert norm.max() / norm.min() > 1.3  # the positions' weights did differ (1.6 here)


def test_fuse_taps_takes_a_cached_form_by_its_prefix(hyp, maps):
    L, G = maps
    other = torch.randn(G.shape, generator=torch.Generator().manual_seed(9))
    f = {"L:stage6": L[:, :192], "L:stage7": L[:, 192:], "G:stage6": G[:, :192], "G:stage7": G[:, 192:],
         "Gloc:stage6": other[:, :192], "Gloc:stage7": other[:, 192:]}
    taps = ("stage6", "stage7")
    for g, ref in (("Gloc", other), ("G", G)):
        assert torch.allclose(torch.cat(hyp.fuse_taps(f, taps, "dam", g), 1), fuse_groups(L, ref, "dam", (192, 320)))
    # "@last": the last tap fused, the others as L (the default's attend="stage7")
    assert torch.allclose(torch.cat(hyp.fuse_taps(f, taps, "dam", "G@last"), 1),
                          fuse_groups(L, G, "dam", (192, 320), (False, True)))
    with pytest.raises(KeyError):  # a form that is not cached is an error, never the plain G in disguise
        hyp.fuse_taps(f, taps, "dam", "Gtop5")


def test_vlad_code_hand_computed(hyp):
    # one map, 3 positions of 2 channels, 2 unit words: positions 0 and 1 go to word 0, position 2 to word 1
    x = torch.tensor([[1.0, 0.0], [0.8, 0.6], [0.0, 1.0]]).T.reshape(1, 2, 1, 3)
    words = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    res0 = torch.tensor([1.0, 0.0]) + torch.tensor([0.8, 0.6]) - 2 * words[0]  # (-0.2, 0.6)
    res1 = torch.tensor([0.0, 1.0]) - words[1]  # zero: stays zero after the intra-normalisation
    v = torch.cat([res0 / res0.norm(), res1])
    v = v.sign() * v.abs().sqrt()
    assert torch.allclose(hyp.vlad_code([x], [words]), (v / v.norm())[None], atol=1e-6)
    # spherical k-means finds two separated directions
    pts = F.normalize(torch.tensor([[1.0, 0.05], [1.0, -0.05], [0.05, 1.0], [-0.05, 1.0]]), dim=1)
    c = hyp._kmeans_unit(pts, 2)
    assert sorted(int(i) for i in (pts @ c.T).argmax(1)[[0, 2]]) == [0, 1]


def test_imagenet_tap_statistics_are_the_batch_norms_training_statistics(hyp):
    # The claim behind --only imagenet: a block's last batch-norm outputs mean beta and std |gamma| over the
    # data its running statistics were taken on. Take them on a batch here (each batch-norm's statistics of
    # this batch, then eval mode) and compare with the batch's own tap statistics.
    from attnloop.backbones.efficientnet_lite import efficientnet_lite
    from attnloop.backbones.preprocess import prepare_images

    net = efficientnet_lite("lite0", pretrained=False, tap="stage6+stage7", input_size=hyp.SIZE, seed=3)
    x = prepare_images(torch.from_numpy(np.random.default_rng(0).integers(0, 256, (6, 3, 120, 160), dtype=np.uint8)),
                       hyp.SIZE, net.mean, net.std)
    g = torch.Generator().manual_seed(0)
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            with torch.no_grad():  # trained-looking affine parameters (the random init has beta 0, gamma 1)
                m.weight.copy_(0.5 + 1.5 * torch.rand(m.weight.shape, generator=g))
                m.bias.copy_(torch.randn(m.bias.shape, generator=g))
            m.reset_running_stats()
            m.momentum = None  # a cumulative average: after one batch, that batch's statistics
    with torch.no_grad():
        net.train()
        net.forward_to_tap(x)
        net.eval()
        L = net.forward_to_tap(x)
    stats = hyp.imagenet_tap_statistics(net)
    L6, L7 = L[:, :192], L[:, 192:]
    mean7, std7 = stats["stage7"]
    # (eval mode normalises by the unbiased variance of the batch: a few % of a standard deviation off)
    assert torch.allclose(L7.mean((0, 2, 3)), mean7, atol=0.05 * float(std7.mean()))
    assert torch.allclose(L7.std((0, 2, 3)), std7, rtol=0.05)
    # stage6 adds three residual blocks' outputs to the first's: the means add exactly
    mean6, _ = stats["stage6"]
    assert torch.allclose(L6.mean((0, 2, 3)), mean6, atol=0.05 * float(L6.std((0, 2, 3)).mean()))
    assert float(mean6.abs().mean()) > 0.5  # four betas of N(0, 1) summed: the check is not a trivial zero


def test_subregion_rnns_over_the_whole_map_are_the_papers_flat_rnns(hyp, maps):
    # one region (the whole map): the library's flat pooling (no merge) at pool_scale 10, the same weights
    from attnloop.descriptor import descriptor_from_attention
    from attnloop.rnn_pool import random_rnn_weights

    L = maps[0][:, :64]
    vectors, sizes = hyp.region_vectors([L], "whole")
    assert sizes == [64 * 7 * 9]
    w = random_rnn_weights(16, 64 * 7 * 9, 64, seed=1000 * 2 + 0)
    ref = descriptor_from_attention(L, torch.zeros_like(L), w, "none", pooling="flat", merge=False)[1]
    assert torch.allclose(hyp.subregion_rnn(vectors, sizes, seed=2, num_rnn=16), ref, atol=1e-6)


def test_subregion_rnns_see_only_their_region(hyp, maps):
    # whole + 2 x 2 on a 7 x 9 map: cells rows 0-3 / 3-6, columns 0-4 / 4-8; a change at (6, 8) reaches the
    # whole map's RNNs and the bottom-right cell's only
    L = maps[0][:1, :32]
    vectors, sizes = hyp.region_vectors([L], hyp.DEFAULT_LAYOUT)
    assert sizes == [32 * 63] + [32 * 4 * 5] * 4
    moved = L.clone()
    moved[0, :, 6, 8] += 1.0
    a = hyp.subregion_rnn(vectors, sizes, seed=0, num_rnn=2)
    b = hyp.subregion_rnn(hyp.region_vectors([moved], hyp.DEFAULT_LAYOUT)[0], sizes, seed=0, num_rnn=2)
    # undo the final L2 (it mixes the regions' scales): every region is unit length before it
    a, b = a.view(5, 128) * 5 ** 0.5, b.view(5, 128) * 5 ** 0.5
    changed = [not torch.allclose(x, y, atol=1e-6) for x, y in zip(a, b)]
    assert changed == [True, False, False, False, True]
