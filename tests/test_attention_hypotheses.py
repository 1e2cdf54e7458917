"""benchmarks/attention_hypotheses.py: its baseline is the library's default, its variants are what they say."""
from __future__ import annotations

import pytest
import torch

from attnloop import AttentionDescriptor
from attnloop.fusion import FUSION_MODES
from attnloop.pooling import fuse_groups


@pytest.fixture(scope="module")
def hyp():
    import importlib.util
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "attention_hypotheses.py"
    spec = importlib.util.spec_from_file_location("attention_hypotheses", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    yield mod
    sys.modules.pop(spec.name, None)


@pytest.fixture(scope="module")
def maps():
    g = torch.Generator().manual_seed(4)
    return torch.randn(2, 512, 7, 9, generator=g), torch.randn(2, 512, 7, 9, generator=g) * 1e-5


@pytest.mark.parametrize("mode", FUSION_MODES)
def test_the_sweeps_baseline_is_the_library_default(hyp, maps, mode):
    # the "paper N, own S" rows must be the default descriptor's numbers, or the sweep compares to nothing
    L, G = maps
    assert torch.allclose(hyp.fused(L, G, mode), fuse_groups(L, G, mode, (192, 320)))
    desc = AttentionDescriptor("efficientnet_lite0", fusion=mode, pretrained=False)
    assert torch.allclose(hyp.descriptor(hyp.fused(L, G, mode)), desc.from_attention(L, G), atol=1e-6)


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
