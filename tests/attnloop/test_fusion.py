"""Tests of attnloop.fusion: hand-computed values, normalisation edge cases, gradcheck, composition."""
from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from attnloop.fusion import (
    FUSION_MODES,
    Fusion,
    dam,
    eam,
    ega,
    fuse,
    gaf,
    minmax_normalize,
    no_attention,
)

OPS = {"none": no_attention, "dam": dam, "eam": eam, "gaf": gaf, "ega": ega}


# ------------------------------------------------------------------ minmax_normalize
def test_minmax_hand_values():
    x = torch.tensor([[[[-2.0, 0.0], [2.0, 6.0]]]])  # negative values included
    out = minmax_normalize(x, dims=(1, 2, 3))
    torch.testing.assert_close(out, torch.tensor([[[[0.0, 0.25], [0.5, 1.0]]]]))


def test_minmax_all_negative():
    x = torch.tensor([[-5.0, -3.0, -1.0]])
    torch.testing.assert_close(minmax_normalize(x, dims=1), torch.tensor([[0.0, 0.5, 1.0]]))


@pytest.mark.parametrize("value", [0.0, 3.5, -7.0])
def test_minmax_constant_gives_zeros_and_finite_grad(value):
    x = torch.full((2, 3, 4, 4), value, dtype=torch.float64, requires_grad=True)
    out = minmax_normalize(x, dims=(1, 2, 3))
    assert torch.equal(out, torch.zeros_like(out))
    out.sum().backward()
    assert torch.isfinite(x.grad).all()


def test_minmax_batch_samples_are_independent():
    normal = torch.arange(12, dtype=torch.float32).reshape(1, 3, 2, 2) * 2.0 - 5.0
    const = torch.full((1, 3, 2, 2), 4.0)
    batch = torch.cat([const, normal, 100.0 * normal])
    out = minmax_normalize(batch, dims=(1, 2, 3))
    assert torch.equal(out[0], torch.zeros(3, 2, 2))
    expected = torch.arange(12, dtype=torch.float32).reshape(3, 2, 2) / 11.0
    torch.testing.assert_close(out[1], expected)
    torch.testing.assert_close(out[2], expected)  # scale of another sample does not leak


def test_minmax_per_channel_dims():
    x = torch.tensor([[[[0.0, 2.0]], [[5.0, 5.0]], [[-1.0, -3.0]]]])  # (1, 3, 1, 2)
    out = minmax_normalize(x, dims=(2, 3))
    torch.testing.assert_close(out, torch.tensor([[[[0.0, 1.0]], [[0.0, 0.0]], [[1.0, 0.0]]]]))


def test_minmax_range_in_unit_interval_and_extremes():
    x = torch.randn(4, 16, 5, 5) * 10
    out = minmax_normalize(x, dims=(1, 2, 3))
    assert out.min() >= 0 and out.max() <= 1
    assert torch.allclose(out.flatten(1).amin(1), torch.zeros(4))
    assert torch.allclose(out.flatten(1).amax(1), torch.ones(4))


def test_minmax_bad_dims():
    with pytest.raises(ValueError, match="out of range"):
        minmax_normalize(torch.rand(2, 3), dims=(2,))
    with pytest.raises(ValueError, match="at least one"):
        minmax_normalize(torch.rand(2, 3), dims=())


def test_minmax_gradcheck():
    x = torch.randn(2, 3, 4, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: minmax_normalize(t, dims=(1, 2, 3)), (x,))
    assert torch.autograd.gradcheck(lambda t: minmax_normalize(t, dims=(2, 3)), (x,))


# ------------------------------------------------------------------ operators by hand
# One sample, two channels of 2x2. Channel 0 = [[0, 1], [2, 3]], channel 1 = [[3, 0], [0, 0]].
G_HAND = torch.tensor([[[[0.0, 1.0], [2.0, 3.0]], [[3.0, 0.0], [0.0, 0.0]]]])
L_HAND = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]], [[-1.0, 5.0], [0.5, 2.0]]]])
# N over (C, H, W): min 0, max 3 -> G / 3.
N_CHW = G_HAND / 3.0
# GAF: per-channel N: ch0 [[0, 1/3], [2/3, 1]], ch1 [[1, 0], [0, 0]]; sum [[1, 1/3], [2/3, 1]];
# outer N (min 1/3, max 1): [[1, 0], [1/2, 1]].
N_GLOBAL = torch.tensor([[[[1.0, 0.0], [0.5, 1.0]]]])


def test_none_by_hand():
    assert no_attention(L_HAND, G_HAND) is L_HAND


def test_dam_by_hand():
    torch.testing.assert_close(dam(L_HAND, G_HAND), L_HAND * N_CHW)
    expected_ch0 = torch.tensor([[0.0, 2.0 / 3.0], [2.0, 4.0]])
    torch.testing.assert_close(dam(L_HAND, G_HAND)[0, 0], expected_ch0)


def test_eam_by_hand():
    torch.testing.assert_close(eam(L_HAND, G_HAND), L_HAND * torch.exp(N_CHW))
    assert math.isclose(eam(L_HAND, G_HAND)[0, 0, 1, 1].item(), 4.0 * math.e, rel_tol=1e-6)


def test_gaf_by_hand():
    out = gaf(L_HAND, G_HAND)
    torch.testing.assert_close(out, L_HAND * N_GLOBAL)
    torch.testing.assert_close(out[0, 1], torch.tensor([[-1.0, 0.0], [0.25, 2.0]]))


def test_ega_by_hand():
    out = ega(L_HAND, G_HAND)
    torch.testing.assert_close(out, L_HAND * torch.exp(N_GLOBAL))
    assert math.isclose(out[0, 0, 1, 0].item(), 3.0 * math.exp(0.5), rel_tol=1e-6)


def test_flat_attention():
    L = torch.rand(2, 4, 3, 3)
    G = torch.full_like(L, 2.0)
    assert torch.equal(dam(L, G), torch.zeros_like(L))
    assert torch.equal(gaf(L, G), torch.zeros_like(L))
    torch.testing.assert_close(eam(L, G), L)
    torch.testing.assert_close(ega(L, G), L)


@pytest.mark.parametrize("mode", FUSION_MODES)
def test_batch_mixed_samples_independent(mode):
    L = torch.rand(3, 4, 5, 5, dtype=torch.float64)
    G = torch.randn(3, 4, 5, 5, dtype=torch.float64)
    G[1] = 0.7  # a constant sample in the middle
    out = fuse(L, G, mode)
    for b in range(3):
        torch.testing.assert_close(out[b:b + 1], fuse(L[b:b + 1], G[b:b + 1], mode))
    assert torch.isfinite(out).all()


def test_global_map_is_shared_by_channels():
    L = torch.ones(2, 6, 4, 4)
    out = gaf(L, torch.randn(2, 6, 4, 4))
    torch.testing.assert_close(out, out[:, :1].expand_as(out))


# ------------------------------------------------------------------ gradients, dtypes, errors
@pytest.mark.parametrize("mode", FUSION_MODES)
def test_gradcheck(mode):
    L = torch.randn(2, 3, 4, 4, dtype=torch.float64, requires_grad=True)
    G = torch.randn(2, 3, 4, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: fuse(a, b, mode), (L, G))


@pytest.mark.parametrize("mode", FUSION_MODES)
def test_constant_attention_backward_finite(mode):
    L = torch.rand(1, 2, 3, 3, dtype=torch.float64, requires_grad=True)
    G = torch.zeros(1, 2, 3, 3, dtype=torch.float64, requires_grad=True)
    fuse(L, G, mode).sum().backward()
    assert torch.isfinite(L.grad).all()
    assert G.grad is None or torch.isfinite(G.grad).all()


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("mode", FUSION_MODES)
def test_dtype_preserved(mode, dtype):
    L = torch.rand(1, 2, 3, 3).to(dtype)
    G = torch.randn(1, 2, 3, 3).to(dtype)
    out = fuse(L, G, mode)
    assert out.dtype == dtype and out.shape == L.shape


@pytest.mark.parametrize("mode", FUSION_MODES)
def test_shape_errors(mode):
    with pytest.raises(ValueError, match="same shape"):
        fuse(torch.rand(1, 2, 3, 3), torch.rand(1, 2, 3, 4), mode)
    with pytest.raises(ValueError, match=r"\(B, C, H, W\)"):
        fuse(torch.rand(2, 3, 3), torch.rand(2, 3, 3), mode)


def test_unknown_mode():
    with pytest.raises(ValueError, match="unknown fusion mode"):
        Fusion("attention")
    with pytest.raises(ValueError, match="unknown fusion mode"):
        fuse(torch.rand(1, 1, 2, 2), torch.rand(1, 1, 2, 2), "xyz")


def test_module_matches_function_and_case():
    L, G = torch.rand(2, 4, 3, 3), torch.randn(2, 4, 3, 3)
    for mode in FUSION_MODES:
        torch.testing.assert_close(Fusion(mode.upper())(L, G), OPS[mode](L, G))
    assert len(list(Fusion("dam").parameters())) == 0


def test_composes_in_sequential():
    class WithAttention(nn.Module):
        """A user's block: the attention is a fixed function of the input, fused by Fusion."""

        def __init__(self, mode):
            super().__init__()
            self.fusion = Fusion(mode)

        def forward(self, x):
            return self.fusion(x, x.pow(2))

    model = nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), nn.ReLU(), WithAttention("ega"),
                          nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Linear(8, 2))
    x = torch.rand(4, 3, 9, 9)
    out = model(x)
    assert out.shape == (4, 2)
    out.sum().backward()
    assert model[0].weight.grad is not None and torch.isfinite(model[0].weight.grad).all()


def test_minmax_a_nan_or_an_infinity_makes_its_slice_nan_and_leaves_the_others():
    x = torch.tensor([[-math.inf, 1.0, 2.0, 3.0], [math.inf, 1.0, 2.0, 3.0], [math.nan, 1.0, 2.0, 3.0],
                      [1.0, 2.0, 3.0, 5.0]])
    out = minmax_normalize(x, dims=1)
    assert torch.isnan(out[:3]).all()  # -inf made every entry NaN, +inf made the finite ones 0 before
    torch.testing.assert_close(out[3], torch.tensor([0.0, 0.25, 0.5, 1.0]))


@pytest.mark.parametrize("shape", [(1, 0, 3, 3), (1, 4, 0, 3), (0, 0, 3, 3)])
def test_fuse_refuses_an_empty_channel_or_spatial_dimension(shape):
    with pytest.raises(ValueError, match="positive C, H and W"):
        fuse(torch.rand(shape), torch.rand(shape), "dam")
    assert fuse(torch.rand(0, 4, 3, 3), torch.rand(0, 4, 3, 3), "gaf").shape == (0, 4, 3, 3)  # an empty batch
