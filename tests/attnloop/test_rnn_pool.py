"""Tests of attnloop.rnn_pool: merge pairing, seeded weights, pooling by hand, gradcheck, module."""
from __future__ import annotations

import io

import pytest
import torch
from torch import nn

from attnloop.rnn_pool import RandomRNNPool, merge_channels, random_rnn_pool, random_rnn_weights


# ------------------------------------------------------------------ merge
def test_merge_pairs_c_with_c_plus_half_by_hand():
    # Channel c holds the constant c: the merge of c and c + 2 (C = 4) is (c + c + 2) / 2 = c + 1.
    x = torch.arange(4, dtype=torch.float32).reshape(1, 4, 1, 1).expand(2, 4, 3, 3)
    out = merge_channels(x)
    assert out.shape == (2, 2, 3, 3)
    torch.testing.assert_close(out[:, 0], torch.full((2, 3, 3), 1.0))
    torch.testing.assert_close(out[:, 1], torch.full((2, 3, 3), 2.0))


def test_merge_not_adjacent_pairs():
    x = torch.zeros(1, 4, 1, 1)
    x[0, 0] = 2.0  # pairs with channel 2, not channel 1
    x[0, 1] = 10.0
    out = merge_channels(x).flatten()
    torch.testing.assert_close(out, torch.tensor([1.0, 5.0]))


def test_merge_odd_channels_error():
    with pytest.raises(ValueError, match="even number of channels"):
        merge_channels(torch.rand(1, 3, 2, 2))
    with pytest.raises(ValueError, match=r"\(B, C, H, W\)"):
        merge_channels(torch.rand(3, 2, 2))


# ------------------------------------------------------------------ weights
def test_weights_range_shape_and_seed():
    w = random_rnn_weights(4, 300, 16, seed=3)
    assert w.shape == (4, 16, 300) and w.dtype == torch.float32
    assert w.min() >= -0.1 and w.max() <= 0.1
    # U[-0.1, 0.1]: mean 0, std 0.2 / sqrt(12) = 0.0577; 19200 samples -> se of the mean ~4e-4.
    assert abs(w.mean().item()) < 3e-3
    assert abs(w.std().item() - 0.2 / 12 ** 0.5) < 2e-3
    assert torch.equal(w, random_rnn_weights(4, 300, 16, seed=3))
    assert not torch.equal(w, random_rnn_weights(4, 300, 16, seed=4))
    # The RNNs differ from each other.
    assert not torch.equal(w[0], w[1])


def test_weights_dtype_device_independent():
    w32 = random_rnn_weights(2, 50, 8, seed=1)
    w64 = random_rnn_weights(2, 50, 8, seed=1, dtype=torch.float64, device="cpu")
    assert w64.dtype == torch.float64
    assert torch.equal(w64, w32.double())


def test_weights_do_not_touch_global_rng():
    torch.manual_seed(123)
    a = torch.rand(3)
    torch.manual_seed(123)
    random_rnn_weights(2, 10, 4, seed=0)
    assert torch.equal(torch.rand(3), a)


def test_weights_bad_sizes():
    with pytest.raises(ValueError, match="num_rnn"):
        random_rnn_weights(0, 10)


# ------------------------------------------------------------------ pooling
def test_pool_by_hand():
    # C=4, H=W=1: merged vector m = [(x0 + x2)/2, (x1 + x3)/2]; two RNNs of 3 outputs each.
    x = torch.tensor([[[[1.0]], [[-2.0]], [[3.0]], [[4.0]]]])
    w = torch.tensor([[[0.1, -0.1], [0.05, 0.0], [-0.02, 0.03]],
                      [[0.0, 0.1], [0.1, 0.1], [-0.1, 0.0]]])
    m = torch.tensor([2.0, 1.0])
    expected = torch.tanh(torch.cat([w[0] @ m, w[1] @ m])).unsqueeze(0)
    torch.testing.assert_close(random_rnn_pool(x, w), expected)
    # without merge the input is the whole 4-vector
    w4 = torch.rand(1, 2, 4)
    torch.testing.assert_close(random_rnn_pool(x, w4, merge=False),
                               torch.tanh(w4[0] @ x.flatten()).unsqueeze(0))


def test_pool_flattening_equals_paper_reshape():
    # Paper: (256, 7, 7) -> (64, 14, 14) then the whole vector into W_r. Same vector as our flatten.
    x = torch.rand(2, 512, 7, 7, dtype=torch.float64)
    w = random_rnn_weights(2, 12544, 64, seed=0, dtype=torch.float64)
    merged = merge_channels(x).reshape(2, 64, 14, 14)
    ref = torch.cat([torch.tanh(merged.reshape(2, -1) @ w[r].t()) for r in range(2)], dim=1)
    torch.testing.assert_close(random_rnn_pool(x, w), ref)


def test_pool_batch_independent():
    w = random_rnn_weights(3, 2 * 3 * 3, 5)
    x = torch.rand(4, 4, 3, 3)
    out = random_rnn_pool(x, w)
    for b in range(4):
        torch.testing.assert_close(out[b:b + 1], random_rnn_pool(x[b:b + 1], w))


def test_pool_gradcheck():
    x = torch.randn(2, 4, 3, 3, dtype=torch.float64, requires_grad=True)
    w = (torch.rand(3, 5, 18, dtype=torch.float64) * 0.2 - 0.1).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: random_rnn_pool(a, b), (x, w))
    module = RandomRNNPool(4, in_size=(3, 3), num_rnn=3, out_features=5).double()
    assert torch.autograd.gradcheck(module, (x,))


def test_pool_shape_errors():
    w = random_rnn_weights(2, 18, 4)
    with pytest.raises(ValueError, match="expect 18"):
        random_rnn_pool(torch.rand(1, 4, 3, 4), w)
    with pytest.raises(ValueError, match="num_rnn, out_features, in_features"):
        random_rnn_pool(torch.rand(1, 4, 3, 3), w[0])
    with pytest.raises(ValueError, match="even"):
        random_rnn_pool(torch.rand(1, 3, 3, 3), w)


def test_pool_casts_weight_dtype():
    w = random_rnn_weights(2, 18, 4)
    out = random_rnn_pool(torch.rand(1, 4, 3, 3, dtype=torch.float64), w)
    assert out.dtype == torch.float64


# ------------------------------------------------------------------ module
def test_module_vgg_dims_and_seed():
    a = RandomRNNPool(512, in_size=(7, 7), num_rnn=16, out_features=64, seed=0)
    assert a.weights.shape == (16, 64, 12544) and a.out_dim == 1024
    x = torch.rand(2, 512, 7, 7)
    out = a(x)
    assert out.shape == (2, 1024)
    assert out.abs().max() <= 1  # tanh range (saturates on this non-negative random input)
    b = RandomRNNPool(512, seed=0)
    assert torch.equal(b(x), out)
    c = RandomRNNPool(512, seed=1)
    assert not torch.allclose(c(x), out)


def test_module_state_dict_roundtrip():
    a = RandomRNNPool(8, in_size=(2, 3), num_rnn=2, out_features=4, seed=5)
    assert list(a.state_dict()) == ["weights"]
    buf = io.BytesIO()
    torch.save(a.state_dict(), buf)
    buf.seek(0)
    b = RandomRNNPool(8, in_size=(2, 3), num_rnn=2, out_features=4, seed=6)
    b.load_state_dict(torch.load(buf))
    assert torch.equal(a.weights, b.weights)
    assert len(list(a.parameters())) == 0


def test_module_other_shapes_and_no_merge():
    # EfficientNet-like tap: 320 channels at 7x7 -> 160*49 inputs.
    pool = RandomRNNPool(320, in_size=7, num_rnn=4, out_features=32)
    assert pool.weights.shape == (4, 32, 160 * 49)
    assert pool(torch.rand(1, 320, 7, 7)).shape == (1, 128)
    odd = RandomRNNPool(3, in_size=(2, 2), num_rnn=2, out_features=4, merge=False)
    assert odd(torch.rand(2, 3, 2, 2)).shape == (2, 8)


def test_module_errors():
    with pytest.raises(ValueError, match="even"):
        RandomRNNPool(3, in_size=(2, 2))
    pool = RandomRNNPool(4, in_size=(3, 3), num_rnn=1, out_features=2)
    with pytest.raises(ValueError, match=r"\(B, 4, 3, 3\)"):
        pool(torch.rand(1, 4, 3, 4))


def test_module_dtype_follows_module():
    pool = RandomRNNPool(4, in_size=(2, 2), num_rnn=1, out_features=3).double()
    assert pool.weights.dtype == torch.float64
    assert pool(torch.rand(1, 4, 2, 2, dtype=torch.float64)).dtype == torch.float64


def test_composes_in_sequential():
    model = nn.Sequential(nn.Conv2d(3, 8, 3, stride=2, padding=1), nn.ReLU(),
                          RandomRNNPool(8, in_size=(4, 4), num_rnn=2, out_features=8), nn.Linear(16, 3))
    out = model(torch.rand(2, 3, 8, 8))
    assert out.shape == (2, 3)
    out.sum().backward()
    assert torch.isfinite(model[0].weight.grad).all() and model[0].weight.grad.abs().sum() > 0
