"""Regression tests of fusion, pooling, rnn_pool, guided_backprop and the backbones on bad input.

Each test pins a defect that the code had: a wrong shape, dtype or value accepted silently, an empty
batch crashing, NaN hidden, a documented behaviour the code did not have.
"""
from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from attnloop.backbones.efficientnet_lite import EfficientNetLite0, efficientnet_lite_taps
from attnloop.backbones.preprocess import prepare_images
from attnloop.fusion import dam, eam, fuse, gaf, minmax_normalize
from attnloop.guided_backprop import guided_backprop, softmax_seeded_gradient
from attnloop.pooling import fuse_groups, gem_regions, regional_code, unit_scale
from attnloop.rnn_pool import RandomRNNPool, random_rnn_pool, random_rnn_weights

NAN = float("nan")


# ------------------------------------------------------------------ rnn_pool
@pytest.mark.parametrize("merge", [True, False])
def test_random_rnn_pool_empty_batch(merge):
    # x.reshape(0, -1) raised "cannot reshape tensor of 0 elements"; the empty batch gives (0, R * O).
    w = random_rnn_weights(3, (4 if merge else 8) * 2 * 2, 5, seed=1, dtype=torch.float64)
    out = random_rnn_pool(torch.rand(0, 8, 2, 2, dtype=torch.float64), w, merge=merge)
    assert out.shape == (0, 15) and out.dtype == torch.float64
    pool = RandomRNNPool(8, in_size=(2, 2), num_rnn=3, out_features=5, seed=1, merge=merge)
    assert pool(torch.rand(0, 8, 2, 2)).shape == (0, 15)


def test_random_rnn_pool_hand_values():
    # tanh(W_r vec(merge(x))) computed by hand for one sample; the flattening change keeps these values.
    x = torch.arange(8, dtype=torch.float64).reshape(1, 8, 1, 1) / 10  # channels 0..7 -> 0.0..0.7
    merged = torch.tensor([0.2, 0.3, 0.4, 0.5], dtype=torch.float64)  # (c + (c + 4)) / 2 / 10
    w = random_rnn_weights(2, 4, 3, seed=5, dtype=torch.float64)
    expected = torch.tanh(torch.stack([w[r] @ merged for r in range(2)]).reshape(-1))
    torch.testing.assert_close(random_rnn_pool(x, w)[0], expected, rtol=0, atol=1e-15)


def test_random_rnn_pool_rejects_integer_maps():
    # An integer map cast the weights (|w| < 0.1) to integers: every weight 0, a zero descriptor, no error.
    x = torch.randint(1, 5, (1, 8, 3, 3))
    w = random_rnn_weights(2, 4 * 3 * 3, 4)
    assert random_rnn_pool(x.float(), w).abs().amax() > 0.1  # the same map as floats is far from zero
    with pytest.raises(TypeError, match="floating"):
        random_rnn_pool(x, w)
    with pytest.raises(TypeError, match="weights must be a floating"):
        random_rnn_pool(x.float(), (w * 100).long())


def test_random_rnn_weights_integer_valued_sizes_and_bad_seed():
    # 2.0 passed the "positive integer" check, then crashed in torch.rand; a seed 1.5 was truncated to 1.
    torch.testing.assert_close(random_rnn_weights(2.0, 6.0, 3.0, seed=4), random_rnn_weights(2, 6, 3, seed=4),
                               rtol=0, atol=0)
    with pytest.raises(ValueError, match="seed"):
        random_rnn_weights(2, 6, 3, seed=1.5)
    with pytest.raises(ValueError, match="dtype"):
        random_rnn_weights(2, 6, 3, dtype=torch.int64)


def test_random_rnn_pool_module_rejects_fractional_sizes():
    # in_size (3.5, 3) became (3, 3) silently; in_channels 8.0 crashed in torch.rand.
    with pytest.raises(ValueError, match="in_size"):
        RandomRNNPool(8, in_size=(3.5, 3), num_rnn=2, out_features=4)
    pool = RandomRNNPool(8.0, in_size=(3, 3), num_rnn=2, out_features=4)
    assert pool(torch.rand(2, 8, 3, 3)).shape == (2, 8)


# ------------------------------------------------------------------ fusion
def test_minmax_nan_propagates_instead_of_zero_map():
    # A NaN made the range NaN, "range > eps" False, and the slice came back as zeros: the NaN was hidden.
    x = torch.tensor([[1.0, NAN, 3.0], [1.0, 2.0, 3.0], [5.0, 5.0, 5.0]])
    out = minmax_normalize(x, dims=1)
    assert torch.isnan(out[0]).all()
    torch.testing.assert_close(out[1:], torch.tensor([[0.0, 0.5, 1.0], [0.0, 0.0, 0.0]]), rtol=0, atol=0)


def test_fusion_with_nan_attention_is_nan():
    # EAM gave L * exp(0) = L for a NaN G, a finite descriptor of a broken gradient.
    L = torch.ones(2, 1, 1, 3)
    G = torch.tensor([[[[0.0, NAN, 4.0]]], [[[0.0, 1.0, 4.0]]]])
    assert torch.isnan(eam(L, G)[0]).all() and torch.isnan(dam(L, G)[0]).all()
    torch.testing.assert_close(dam(L, G)[1], torch.tensor([[[0.0, 0.25, 1.0]]]))
    torch.testing.assert_close(eam(L, G)[1], torch.exp(torch.tensor([[[0.0, 0.25, 1.0]]])))


def test_minmax_rejects_integer_input():
    # an integer x came back float32, not "its dtype".
    with pytest.raises(TypeError, match="floating"):
        minmax_normalize(torch.tensor([[1, 2, 3]]), dims=1)
    x = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)
    assert minmax_normalize(x, dims=1).dtype == torch.float64


def test_fusion_rejects_mixed_or_integer_dtypes():
    # L float32 with G float64 returned float64 (the dtype followed neither input alone); int G gave float32.
    L = torch.rand(1, 2, 3, 3)
    with pytest.raises(ValueError, match="one dtype"):
        dam(L, torch.rand(1, 2, 3, 3, dtype=torch.float64))
    with pytest.raises(TypeError, match="G must be a floating"):
        fuse(L, torch.ones(1, 2, 3, 3, dtype=torch.int64), "gaf")


def test_dam_gaf_gradcheck_float64():
    # the NaN-propagating comparison leaves finite inputs' values and derivatives as they were
    L = torch.rand(2, 3, 3, 4, dtype=torch.float64, requires_grad=True)
    G = torch.randn(2, 3, 3, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(dam, (L, G))
    assert torch.autograd.gradcheck(gaf, (L, G))


# ------------------------------------------------------------------ pooling
def test_unit_scale_per_sample_for_one_dimensional_batches():
    # (B,) reduced amax over dim=(), i.e. over the whole batch: [2, -4] gave [0.5, -1], not per sample.
    torch.testing.assert_close(unit_scale(torch.tensor([2.0, -4.0, 0.0])), torch.tensor([1.0, -1.0, 0.0]))
    torch.testing.assert_close(unit_scale(torch.tensor([[2.0, -4.0], [0.5, 0.0]], dtype=torch.float64)),
                               torch.tensor([[0.5, -1.0], [1.0, 0.0]], dtype=torch.float64), rtol=0, atol=0)


def test_gem_rejects_infinite_p_and_large_p_tends_to_max():
    # p = inf gave 0.9776 for every cell whatever the map; a large finite p approaches the max.
    x = torch.tensor([[[[0.1, 0.2], [0.3, 0.8]]]], dtype=torch.float64)
    with pytest.raises(ValueError, match="positive and finite"):
        gem_regions(x, p=math.inf)
    with pytest.raises(ValueError, match="positive and finite"):
        regional_code(x, p=math.inf)
    out = gem_regions(x, p=200.0, levels=(1,))
    expected = (x.pow(200).mean()) ** (1 / 200)  # the definition; about 0.8 * 4^(-1/200)
    torch.testing.assert_close(out[0, 0, 0], expected, rtol=1e-12, atol=0)
    assert abs(float(out) - 0.8) < 0.006


def test_gem_and_code_reject_empty_maps_with_clear_errors():
    # H = 0 with B > 0 raised IndexError from amax; B = 0 stays an empty result.
    with pytest.raises(ValueError, match=r"\(1, 2, 0, 4\)"):
        gem_regions(torch.rand(1, 2, 0, 4))
    with pytest.raises(ValueError, match=r"\(1, 2, 0, 4\)"):
        regional_code(torch.rand(1, 2, 0, 4))
    assert regional_code(torch.rand(0, 6, 3, 3, dtype=torch.float64), groups=(2, 4)).shape == (0, 30)


def test_fuse_groups_rejects_non_tensors_and_integer_maps():
    with pytest.raises(TypeError, match="tap must be a torch.Tensor"):
        fuse_groups([1.0], torch.rand(1, 2, 3, 3), "dam")  # was AttributeError: 'list' ... 'ndim'
    with pytest.raises(TypeError, match="grad must be a floating"):
        fuse_groups(torch.rand(1, 2, 3, 3), torch.ones(1, 2, 3, 3, dtype=torch.int64), "dam")


# ------------------------------------------------------------------ guided backprop
def test_guided_backprop_rejects_non_tensors():
    head = nn.Sequential(nn.Flatten(), nn.Linear(4, 3))
    with pytest.raises(TypeError, match="tap must be a torch.Tensor"):
        softmax_seeded_gradient([[1.0, 2.0, 3.0, 4.0]], head)
    with pytest.raises(TypeError, match="images must be a torch.Tensor"):
        guided_backprop(nn.Identity(), [[0.5]])


# ------------------------------------------------------------------ backbones
@pytest.mark.parametrize("size", [(224, 224, 3), (100.7, 224), (0, 224), "224", True])
def test_efficientnet_input_size_validated(size):
    # (224, 224, 3) passed as (224, 224) (the length check came after the truncation); 100.7 became 100.
    with pytest.raises(ValueError, match="input_size"):
        efficientnet_lite_taps(size)
    with pytest.raises(ValueError, match="input_size"), torch.device("meta"):
        EfficientNetLite0(input_size=size)


def test_efficientnet_input_size_valid_forms():
    assert efficientnet_lite_taps((120.0, 160))["stage7"] == (15, 320, (4, 5))
    assert efficientnet_lite_taps(64)["stage7"][2] == (2, 2)


def test_prepare_images_rejects_non_float_dtype():
    # dtype=torch.int64 cast [0, 1) images to int (all zero) and then returned float32 garbage.
    with pytest.raises(ValueError, match="dtype"):
        prepare_images(torch.rand(1, 3, 4, 4), None, None, None, torch.int64)


@pytest.mark.parametrize("size", [(2,), (2, 2, 2), (2.5, 2), (0, 2)])
def test_prepare_images_size_validated(size):
    # (2,) raised IndexError, (2, 2, 2) was read as (2, 2), 2.5 as 2.
    with pytest.raises(ValueError, match="size"):
        prepare_images(torch.rand(1, 3, 4, 4), size, None, None)


@pytest.mark.parametrize("mean,std", [((NAN, 0.5, 0.5), None), (None, (math.inf, 1.0, 1.0))])
def test_prepare_images_mean_std_finite(mean, std):
    # a NaN mean gave a NaN network input, an infinite std an all-zero one, silently
    with pytest.raises(ValueError, match="finite"):
        prepare_images(torch.rand(1, 3, 4, 4), None, mean, std)


def test_prepare_images_empty_batch_own_size_and_values():
    # an empty (0, 3, 0, 0) batch at its own size raised "size must be positive ... got None"
    out = prepare_images(torch.rand(0, 3, 0, 0, dtype=torch.float64), None, None, None)
    assert out.shape == (0, 3, 0, 0) and out.dtype == torch.float64
    x = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64).view(1, 3, 1, 1).expand(1, 3, 2, 2)
    out = prepare_images(x, None, (0.5, 0.5, 0.5), (0.25, 0.5, 1.0))
    expected = torch.tensor([-2.0, 0.0, 0.5], dtype=torch.float64).view(1, 3, 1, 1).expand(1, 3, 2, 2)
    torch.testing.assert_close(out, expected, rtol=0, atol=1e-15)
