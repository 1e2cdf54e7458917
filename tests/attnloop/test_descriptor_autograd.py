"""The differentiable descriptor: autograd against central finite differences, float64.

The finite-difference references use small random CNNs with a smooth activation (softplus): a ReLU
network has kinks that a central difference crosses (with millions of ReLU6 units, EfficientNet-Lite0's
image derivative converges only at eps ~ 1e-8), which would test the difference, not autograd. The
max-pools, the clamps at their outputs and the batch-norm of the real backbones are all there.
"""
from __future__ import annotations

import pytest
import torch
from torch import nn

from attnloop import AttentionDescriptor, GuidedBackprop, HookedBackbone, guided_backprop
from attnloop.backbones import efficientnet_lite0
from attnloop.descriptor import descriptor_from_attention
from attnloop.fusion import FUSION_MODES
from attnloop.guided_backprop import _clamp_scope, clamp_negative_grad, softmax_seeded_gradient

EPS = 1e-6  # central differences in float64: truncation ~eps^2, roundoff ~1e-16 / eps
RTOL = 1e-4  # required agreement; measured agreement is ~1e-7


def smooth_vgg(seed: int = 0) -> nn.Sequential:
    """A VGG-like float64 CNN for 32 x 32 images: L = the second max-pool, two max-pools after it."""
    torch.manual_seed(seed)
    act = nn.Softplus
    net = nn.Sequential(
        nn.Conv2d(3, 8, 3, padding=1), act(), nn.MaxPool2d(2),  # 0-2
        nn.Conv2d(8, 12, 3, padding=1), nn.BatchNorm2d(12), act(), nn.MaxPool2d(2),  # 3-6: L = "6"
        nn.Conv2d(12, 16, 3, padding=1), act(), nn.MaxPool2d(2),  # 7-9
        nn.Conv2d(16, 16, 3, padding=1), act(), nn.MaxPool2d(2),  # 10-12
        nn.Flatten(), nn.Linear(16 * 2 * 2, 10),
    ).double()
    with torch.no_grad():
        net[4].running_mean.uniform_(-0.1, 0.1)
        net[4].running_var.uniform_(0.5, 2.0)
        net[-1].weight.mul_(10.0)  # a peaky softmax, so the seed is far from uniform
    return net.eval()


class SmoothProtocolNet(nn.Module):
    """The same layers as a protocol backbone (preprocess / forward_to_tap / forward_from_tap)."""

    tap_shape = (12, 8, 8)

    def __init__(self) -> None:
        super().__init__()
        self.net = smooth_vgg()

    def preprocess(self, images):
        return images.to(torch.float64)

    def forward_to_tap(self, x):
        return self.net[:7](x)

    def forward_from_tap(self, tap, transition=None):
        t = transition or (lambda v: v)
        x = t(tap)
        x = t(self.net[7:10](x))
        x = t(self.net[10:13](x))
        return self.net[13:](x)


def images_and_direction(batch: int = 2, size: int = 32, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    x = 0.1 + 0.8 * torch.rand(batch, 3, size, size, dtype=torch.float64, generator=g)
    v = torch.randn(x.shape, dtype=torch.float64, generator=g)
    return x, v, g


def directional(f, x: torch.Tensor, v: torch.Tensor, u: torch.Tensor) -> tuple[float, float]:
    """(autograd, central difference) directional derivative of <u, f(x)> along v."""
    xr = x.clone().requires_grad_(True)
    (gx,) = torch.autograd.grad((u * f(xr)).sum(), xr)
    with torch.no_grad():
        fd = (u * (f(x + EPS * v) - f(x - EPS * v))).sum() / (2 * EPS)
    return float((gx * v).sum()), float(fd)


def at_perturbed_weight(weight: torch.Tensor, v: torch.Tensor, f):
    """(f() at weight + EPS v, f() at weight - EPS v), the weight restored after: a central difference's ends."""
    base = weight.detach().clone()
    with torch.no_grad():
        weight.copy_(base + EPS * v)
        plus = f()
        weight.copy_(base - EPS * v)
        minus = f()
        weight.copy_(base)
    return plus, minus


@pytest.mark.parametrize("kind", ["hooked", "protocol"])
def test_image_directional_derivative_every_fusion(kind):
    x, v, g = images_and_direction()
    for mode in FUSION_MODES:
        if kind == "hooked":
            desc = AttentionDescriptor(smooth_vgg(), tap="6", input_size=(32, 32), fusion=mode, differentiable=True)
            assert desc.backbone.clamp_at_tap and desc.backbone.transitions == ("9", "12")
        else:
            desc = AttentionDescriptor(SmoothProtocolNet(), fusion=mode, differentiable=True)
        desc = desc.double()
        u = torch.randn(2, desc.out_dim, dtype=torch.float64, generator=g)
        ad, fd = directional(desc, x, v, u)
        assert abs(fd) > 1e-4, mode  # a derivative that is there
        assert abs(ad - fd) <= RTOL * abs(fd), (mode, ad, fd)


def test_attention_gradient_directional_derivative_is_second_order():
    # G itself (a first derivative of the network) against finite differences of G: second order.
    x, v, g = images_and_direction()
    net = HookedBackbone(smooth_vgg(), "6", input_size=(32, 32))
    u = torch.randn(2, *net.tap_shape, dtype=torch.float64, generator=g)
    ad, fd = directional(lambda im: guided_backprop(net, im, create_graph=True)[1], x, v, u)
    assert abs(fd) > 1e-6 and abs(ad - fd) <= RTOL * abs(fd)


@pytest.mark.parametrize("layer", ["3", "10", "14"])  # below the tap, after it, the linear head
def test_weight_directional_derivative(layer):
    net = smooth_vgg()
    desc = AttentionDescriptor(net, tap="6", input_size=(32, 32), fusion="dam", differentiable=True).double()
    x, _, g = images_and_direction()
    weight = net.get_submodule(layer).weight
    v = torch.randn(weight.shape, dtype=torch.float64, generator=g)
    u = torch.randn(2, desc.out_dim, dtype=torch.float64, generator=g)
    (gw,) = torch.autograd.grad((u * desc(x)).sum(), weight)
    ad = float((gw * v).sum())
    fp, fm = at_perturbed_weight(weight, v, lambda: (u * desc(x)).sum())
    fd = float((fp - fm) / (2 * EPS))
    assert abs(fd) > 1e-5 and abs(ad - fd) <= RTOL * abs(fd), (ad, fd)


def test_clamps_are_identities_for_the_forward_path():
    # Inside a seeded-gradient computation a clamp's forward op must differentiate as the identity
    # once the seeded backward is done; outside one it always clamps (the public helper's contract).
    x = torch.tensor([1.0, -2.0], dtype=torch.float64, requires_grad=True)
    seed = torch.tensor([-1.0, 3.0], dtype=torch.float64)
    (g,) = torch.autograd.grad(clamp_negative_grad(x), x, seed)
    assert g.tolist() == [0.0, 3.0]
    with _clamp_scope():
        y = clamp_negative_grad(x)
    (g,) = torch.autograd.grad(y, x, seed)
    assert g.tolist() == [-1.0, 3.0]
    # ... which is what makes the differentiable G right: with the clamps left on it is not.
    torch.manual_seed(0)
    l1, l2 = nn.Linear(6, 5).double(), nn.Linear(5, 4).double()

    def head(t):
        return l2(clamp_negative_grad(nn.functional.softplus(l1(t))))

    L = torch.randn(3, 6, dtype=torch.float64, requires_grad=True)
    vl, u = torch.randn(3, 6, dtype=torch.float64), torch.randn(3, 6, dtype=torch.float64)
    (gl,) = torch.autograd.grad((u * softmax_seeded_gradient(L, head, guided=False, create_graph=True)).sum(), L)
    fd = (u * (softmax_seeded_gradient(L + EPS * vl, head, False) - softmax_seeded_gradient(L - EPS * vl, head, False)))
    fd = float(fd.sum() / (2 * EPS))
    assert abs(float((gl * vl).sum()) - fd) <= RTOL * abs(fd)


def test_gradcheck_tiny_relu_cnn():
    # torch.autograd.gradcheck (full Jacobian, float64) on a tiny ReLU CNN with max-pools and clamps.
    torch.manual_seed(3)
    net = nn.Sequential(
        nn.Conv2d(3, 4, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),  # L = "2": 4 x 4 x 4
        nn.Conv2d(4, 6, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),
        nn.Flatten(), nn.Linear(6 * 2 * 2, 5),
    ).double()
    with torch.no_grad():
        net[-1].weight.mul_(5.0)
    desc = AttentionDescriptor(net, tap="2", input_size=(8, 8), fusion="dam", num_rnn=2, out_features=4,
                               differentiable=True).double()
    x = (0.1 + 0.8 * torch.rand(1, 3, 8, 8, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(desc, (x,), eps=1e-6, atol=1e-6, rtol=1e-4)
    gbp = GuidedBackprop(desc.backbone, create_graph=True)
    assert torch.autograd.gradcheck(lambda im: gbp(im)[1], (x,), eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.fixture(scope="module")
def lite64_shared():
    # the paper's flat pooling at stage7: the regional GeM's floor is a kink that central differences straddle
    desc = AttentionDescriptor("efficientnet_lite0", fusion="dam", pretrained=False, seed=0, differentiable=True,
                               tap="stage7", pooling="flat", num_rnn=16).double()
    net = desc.backbone
    with torch.no_grad():
        # Random weights: the features fade to ~1e-9 by the head and the softmax is flat to 1e-10, so
        # G = J^T S is a cancellation (S_k - |S|^2) at the edge of float64. Logits of std 2 instead.
        logits = net(0.1 + 0.8 * torch.rand(4, 3, 64, 64, dtype=torch.float64))
        net._fc.weight.mul_(2.0 / float(logits.std()))
    return desc


@pytest.fixture
def lite64(lite64_shared):
    # built once (module scope); every test starts with no accumulated gradient, whatever ran before it
    lite64_shared.zero_grad(set_to_none=True)
    yield lite64_shared
    lite64_shared.zero_grad(set_to_none=True)


def test_efficientnet_head_second_order_every_fusion(lite64):
    # The weights after the tap reach the descriptor only through G (second order through the head);
    # they do not move the forward activations, so no ReLU6 kink is crossed.
    net = lite64.backbone
    x, _, g = images_and_direction(batch=2, size=64)
    weight = net._fc.weight
    v = torch.randn(weight.shape, dtype=torch.float64, generator=g) * weight.detach().std()  # a relative step
    u = torch.randn(2, 1024, dtype=torch.float64, generator=g)
    w = lite64.pool.weights
    modes = FUSION_MODES[1:]  # "none" does not use G
    tap, grad = guided_backprop(net, x, create_graph=True)
    ads = []
    for mode in modes:
        code = descriptor_from_attention(tap, grad, w, mode, pooling="flat")[1]
        (gw,) = torch.autograd.grad((u * code).sum(), weight, retain_graph=True)
        ads.append(float((gw * v).sum()))
    del tap, grad  # the graph saved the weight; it is perturbed in place below
    (tp, gp), (tm, gm) = at_perturbed_weight(weight, v, lambda: guided_backprop(net, x))
    assert torch.equal(tp, tm)  # the forward below the tap does not depend on the head
    for mode, ad in zip(modes, ads):
        plus = descriptor_from_attention(tp, gp, w, mode, pooling="flat")[1]
        minus = descriptor_from_attention(tm, gm, w, mode, pooling="flat")[1]
        fd = float((u * (plus - minus)).sum() / (2 * EPS))
        assert abs(fd) > 1e-4 and abs(ad - fd) <= RTOL * abs(fd), (mode, ad, fd)


def test_every_backbone_parameter_gets_a_gradient(lite64):
    assert all(p.requires_grad for p in lite64.backbone.parameters())  # differentiable: not frozen
    x = torch.rand(2, 3, 64, 64, dtype=torch.float64, requires_grad=True)
    d = lite64(x)
    assert d.grad_fn is not None
    (d[0] @ d[1]).backward()  # a contrastive-like scalar
    grads = {n: p.grad for n, p in lite64.backbone.named_parameters()}
    assert all(gr is not None and gr.abs().max() > 0 for gr in grads.values()), \
        [n for n, gr in grads.items() if gr is None or not gr.abs().max() > 0]
    assert x.grad is not None and x.grad.abs().max() > 0


def test_differentiable_values_equal_the_fast_path(lite64):
    # the same float64 backbone and recipe, detached
    fast = AttentionDescriptor(lite64.backbone, recipe=lite64.recipe)
    x = torch.rand(2, 3, 64, 64, dtype=torch.float64)
    a, b = lite64.parts(x), fast.parts(x)
    assert torch.equal(a.tap.detach(), b.tap)
    for name in ("grad", "fused", "descriptor"):
        # The detached path's G is EfficientNet's closed form (another summation order): equal to
        # float64 rounding relative to the map's largest entry.
        ref, got = getattr(a, name).detach(), getattr(b, name)
        assert (ref - got).abs().max() <= 1e-12 * ref.abs().max(), name
    assert b.descriptor.grad_fn is None and b.grad.grad_fn is None
    with torch.no_grad():  # nothing to differentiate: the detached values
        c = lite64(x)
    assert c.grad_fn is None and torch.allclose(c, a.descriptor, rtol=1e-12)
    assert a.descriptor.grad_fn is not None  # the weights require grad
    assert all(p.grad is None for p in lite64.parameters())


def test_default_descriptor_stays_frozen_and_detached():
    desc = AttentionDescriptor("efficientnet_lite0", pretrained=False)
    assert not any(p.requires_grad for p in desc.backbone.parameters())
    d = desc(torch.rand(1, 3, 64, 64))
    assert d.grad_fn is None and not d.requires_grad
    with pytest.raises(ValueError, match="differentiable=True"):  # never a silently detached output
        desc(torch.rand(1, 3, 64, 64, requires_grad=True))


def test_attended_stage_G_is_second_order_through_the_head():
    # attend="stage7" of the joined tap: G at stage7 only; its derivative w.r.t. the classifier's weights
    # (second order through the head) against central differences, and L's stage6 part still a function
    # of the images.
    net = efficientnet_lite0(pretrained=False, seed=0, tap="stage6+stage7", attend="stage7").double()
    with torch.no_grad():
        logits = net(0.1 + 0.8 * torch.rand(4, 3, 64, 64, dtype=torch.float64))
        net._fc.weight.mul_(2.0 / float(logits.std()))
    x, _, g = images_and_direction(batch=2, size=64)
    weight = net._fc.weight
    v = torch.randn(weight.shape, dtype=torch.float64, generator=g) * weight.detach().std()
    u = torch.randn(2, 512, 7, 7, dtype=torch.float64, generator=g)
    xr = x.clone().requires_grad_(True)
    tap, grad = guided_backprop(net.requires_grad_(True), xr, create_graph=True)
    assert float(grad.detach()[:, :192].abs().max()) == 0 and grad.requires_grad
    (gw,) = torch.autograd.grad((u * grad).sum(), weight, retain_graph=True)
    (gx,) = torch.autograd.grad(tap[:, :192].sum(), xr)
    assert float(gx.abs().max()) > 0
    ad = float((gw * v).sum())
    (_, gp), (_, gm) = at_perturbed_weight(weight, v, lambda: guided_backprop(net, x))
    fd = float((u * (gp - gm)).sum() / (2 * EPS))
    assert abs(fd) > 1e-6 and abs(ad - fd) <= RTOL * abs(fd), (ad, fd)
