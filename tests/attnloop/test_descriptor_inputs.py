"""Descriptor input handling: dtype casts, range and finiteness checks, eval mode during the computation."""
from __future__ import annotations

import pytest
import torch
from torch import nn

from attnloop import AttentionDescriptor, GuidedBackprop, guided_backprop
from attnloop.backbones import FLOAT_RANGE_TOLERANCE, check_images, efficientnet_lite0, prepare_images


@pytest.fixture(scope="module")
def lite():
    return AttentionDescriptor("efficientnet_lite0", pretrained=False, seed=0, tap="stage7")  # 224 x 224, as below


@pytest.fixture(scope="module")
def frames():
    g = torch.Generator().manual_seed(2)
    return torch.randint(0, 256, (3, 3, 96, 128), dtype=torch.uint8, generator=g)


def test_float64_images_into_a_float32_model(lite, frames):
    x32 = frames.float() / 255.0
    d32 = lite(x32)
    d64 = lite(x32.double())  # was a dtype RuntimeError
    assert d64.dtype == torch.float32
    assert torch.allclose(d64, d32, atol=1e-6)
    half = lite(x32.half())  # a half-precision frame is upcast
    assert half.dtype == torch.float32 and ((half * d32).sum(1) > 0.99).all()


def test_double_model_on_float64_and_uint8_images(lite, frames):
    # fusion "none": random weights give a flat softmax, whose G is a float32 cancellation
    desc = AttentionDescriptor(lite.backbone, fusion="none", seed=0)
    desc64 = AttentionDescriptor(efficientnet_lite0(pretrained=False, seed=0), fusion="none", seed=0).double()
    x = frames.double() / 255.0
    a = desc64(x)
    assert a.dtype == torch.float64 and desc64.parts(frames).descriptor.dtype == torch.float64
    assert torch.allclose(a, desc(x).double(), atol=1e-5)


@pytest.mark.parametrize("scale", [255.0, -1.0, 2.0])
def test_float_images_outside_unit_range_are_refused(lite, frames, scale):
    bad = frames.float() / 255.0 * scale
    with pytest.raises(ValueError, match=r"values in \[0, 1\]"):
        lite(bad)
    if scale == 255.0:
        with pytest.raises(ValueError, match="divide by 255 or pass uint8"):
            lite(bad)


def test_small_overshoot_is_accepted(lite, frames):
    x = frames.float() / 255.0
    x[0, 0, 0, 0] = 1.0 + 0.5 * FLOAT_RANGE_TOLERANCE  # e.g. a bicubic resize's ringing
    x[0, 1, 0, 0] = -0.5 * FLOAT_RANGE_TOLERANCE
    assert torch.isfinite(lite(x)).all()


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
def test_non_finite_pixels_are_refused_with_their_place(lite, frames, value):
    x = frames.float() / 255.0
    x[1, 2, 5, 7] = value
    with pytest.raises(ValueError, match=r"1 non-finite pixel value\(s\).*\(1, 2, 5, 7\)"):
        lite(x)
    with pytest.raises(ValueError, match="non-finite"):
        prepare_images(x, (224, 224), None, None)
    with pytest.raises(ValueError, match="non-finite"):
        guided_backprop(lite.backbone, x)


def test_check_images_errors_name_the_expectation():
    with pytest.raises(TypeError, match="torch.Tensor"):
        check_images(torch.zeros(1, 3, 4, 4).numpy())
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\)"):
        check_images(torch.zeros(1, 4, 4, 3))
    check_images(torch.zeros(0, 3, 4, 4))  # empty: nothing to check


class BatchDependent(nn.Module):
    """A protocol backbone with batch-norm and dropout: in train mode a result depends on its batch."""

    tap_shape = (8, 4, 4)

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.trunk = nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), nn.BatchNorm2d(8), nn.ReLU(), nn.AdaptiveAvgPool2d(4))
        self.head = nn.Sequential(nn.Flatten(), nn.Dropout(0.5), nn.Linear(8 * 16, 10))
        with torch.no_grad():
            self.trunk[1].running_mean.uniform_(-0.2, 0.2)
            self.trunk[1].running_var.uniform_(0.5, 2.0)

    def preprocess(self, images):
        return images.float() / 255.0 if images.dtype == torch.uint8 else images.float()

    def forward_to_tap(self, x):
        return self.trunk(x)

    def forward_from_tap(self, tap, transition=None):
        return self.head(tap)


def test_train_mode_changes_nothing(frames):
    net = BatchDependent()
    ref_eval = AttentionDescriptor(net, seed=0).eval()(frames)
    ref_single = [AttentionDescriptor(net, seed=0)(frames[i:i + 1]) for i in range(3)]
    stats = net.trunk[1].running_mean.clone()
    parent = nn.Sequential(AttentionDescriptor(net, seed=0)).train()  # e.g. inside a model being trained
    assert net.training and net.trunk[1].training
    out = parent(frames)
    assert torch.allclose(out, ref_eval, atol=1e-6)
    for i in range(3):  # an image's descriptor does not depend on the rest of its batch
        assert torch.allclose(out[i:i + 1], ref_single[i], atol=1e-6)
    assert net.training and net.trunk[1].training and net.head[1].training  # modes restored
    assert torch.equal(net.trunk[1].running_mean, stats)  # no running-statistics update
    # GuidedBackprop alone, in a parent in train mode
    gbp = nn.ModuleDict({"gbp": GuidedBackprop(net)}).train()
    _, g_train = gbp["gbp"](frames)
    net.eval()
    _, g_eval = guided_backprop(net, frames)
    assert torch.allclose(g_train, g_eval, atol=1e-7, rtol=1e-5) and g_eval.abs().max() > 0
    net.train()


def test_mixed_modes_are_restored_exactly(frames):
    net = BatchDependent().train()
    net.head.eval()  # a frozen head in a training trunk
    before = {n: m.training for n, m in net.named_modules()}
    guided_backprop(net, frames[:1])
    assert {n: m.training for n, m in net.named_modules()} == before

    class Boom(BatchDependent):
        def forward_from_tap(self, tap, transition=None):
            raise RuntimeError("boom")

    bad = Boom().train()
    with pytest.raises(RuntimeError, match="boom"):
        guided_backprop(bad, frames[:1])
    assert all(m.training for m in bad.modules())  # restored after an exception too


def test_fusion_is_the_recipes_and_read_only():
    # it was a Fusion submodule that nothing read: reassigning it changed the repr and not the output
    d = AttentionDescriptor("efficientnet_lite0", fusion="gaf", pretrained=False)
    assert d.fusion == "gaf" == d.recipe.fusion and "fusion='gaf'" in repr(d)
    with pytest.raises(AttributeError):
        d.fusion = "dam"


@pytest.mark.parametrize("settings", [{}, {"fusion": "dam"}, {"fusion": "dam", "tap": "stage6+stage7",
                                                                 "attend": "stage6+stage7"},
                                      {"fusion": "dam", "num_rnn": 16}])
def test_built_under_inference_mode_then_used_with_autograd(settings):
    # the weights were inference tensors, which the seeded backward (no closed form with attend on both
    # stages) cannot save: built under inference_mode, it must equal one built outside
    x = torch.randint(0, 256, (1, 3, 64, 80), dtype=torch.uint8)
    with torch.inference_mode():
        inside = AttentionDescriptor("efficientnet_lite0", pretrained=False, **settings)
    outside = AttentionDescriptor("efficientnet_lite0", pretrained=False, **settings)
    torch.testing.assert_close(inside(x), outside(x))
    with torch.inference_mode():
        net = nn.Sequential(nn.Conv2d(3, 4, 3), nn.ReLU(), nn.Flatten(), nn.Linear(4 * 30 * 30, 5))
    with pytest.raises(ValueError, match="inference tensors.*build it outside"):
        AttentionDescriptor(net, tap="1", input_size=(32, 32))
    with torch.inference_mode():
        lite = efficientnet_lite0(pretrained=False, tap="stage6+stage7", attend="stage6+stage7")
    with pytest.raises(ValueError, match="inference tensors.*build it outside"):  # a library backbone module too
        AttentionDescriptor(lite)


def test_the_functional_descriptor_checks_what_the_recipe_checks():
    from attnloop.descriptor import descriptor_from_attention
    from attnloop.pooling import regional_code_dim
    from attnloop.rnn_pool import random_rnn_weights

    L, G = torch.rand(1, 8, 3, 3), torch.rand(1, 8, 3, 3)
    w = random_rnn_weights(2, regional_code_dim((8,)), 4)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="pool_scale must be positive and finite"):
            descriptor_from_attention(L, G, w, pool_scale=bad)
    for groups in ((-5,), (), (0, 8), (2.5,)):
        with pytest.raises(ValueError, match="positive channel counts"):
            regional_code_dim(groups)


def test_an_empty_batch_stays_in_the_graph_when_differentiable():
    torch.manual_seed(0)
    net = nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2), nn.Flatten(),
                        nn.Linear(8 * 16 * 16, 10))
    d = AttentionDescriptor(net, tap="2", input_size=(32, 32), differentiable=True)
    x = torch.rand(0, 3, 32, 32, requires_grad=True)
    out = d(x)
    assert out.shape == (0, d.out_dim) and out.requires_grad
    out.sum().backward()  # the last, empty chunk of a split batch: no error, zero gradients
    assert torch.equal(net[0].weight.grad, torch.zeros_like(net[0].weight))
    with torch.no_grad():
        assert not d(x).requires_grad


@pytest.mark.parametrize("fusion", ["dam", "none"])
def test_images_that_require_grad_need_differentiable(frames, fusion):
    """A detached output would make backward() fail with torch's bare message, far from the cause."""
    model = AttentionDescriptor("efficientnet_lite0", pretrained=False, seed=0, tap="stage7", fusion=fusion)
    images = (frames[:1].float() / 255).requires_grad_(True)
    with pytest.raises(ValueError, match=r"differentiable=False.*differentiable=True"):
        model(images)
    with torch.no_grad():  # no autograd asked for: nothing to lose
        assert model(images).shape == (1, model.out_dim)
    assert model(images.detach()).shape == (1, model.out_dim)
    grad_model = AttentionDescriptor("efficientnet_lite0", pretrained=False, seed=0, tap="stage7", fusion=fusion,
                                     differentiable=True)
    grad_model(images).sum().backward()
    assert images.grad is not None and float(images.grad.abs().sum()) > 0
