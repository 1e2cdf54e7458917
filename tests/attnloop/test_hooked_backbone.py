"""Attention in your own model: AttentionDescriptor(backbone=module, tap="name") on any classifier."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch import nn
from torch.autograd.functional import vjp

from attnloop import AttentionDescriptor, HookedBackbone, guided_backprop, softmax_seeded_gradient
from attnloop.backbones import efficientnet_lite0


def vgg_like(seed: int = 0) -> nn.Sequential:
    """conv-relu-pool x 3 and a linear head on 32 x 32 images; float64, a peaky softmax."""
    torch.manual_seed(seed)
    net = nn.Sequential(
        nn.Conv2d(3, 8, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),  # 0 1 2 -> (8, 16, 16)
        nn.Conv2d(8, 12, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),  # 3 4 5 -> (12, 8, 8)
        nn.Conv2d(12, 16, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),  # 6 7 8 -> (16, 4, 4)
        nn.Flatten(), nn.Linear(16 * 4 * 4, 10),  # 9 10
    ).double()
    with torch.no_grad():
        net[10].weight.mul_(20.0)
    return net


def seeded_logit_gradient(logits: torch.Tensor) -> torch.Tensor:
    """(dS/dz)^T S in closed form: S * (S - |S|^2)."""
    s = logits.softmax(1)
    return s * (s - (s * s).sum(1, keepdim=True))


def hand_built_gradient(net: nn.Sequential, x: torch.Tensor, clamp_at_tap: bool, tap_end: int) -> torch.Tensor:
    """G at L = net[:tap_end](x): the linear head by hand, clamps at pool8 and pool5 (and at L when asked)."""
    with torch.no_grad():
        L = net[:tap_end](x)
        p5 = net[tap_end:6](L)
        p8 = net[6:9](p5)
        logits = net[9:](p8)
        g_p8 = (seeded_logit_gradient(logits) @ net[10].weight).view_as(p8).clamp(min=0)
    _, g_p5 = vjp(net[6:9], p5, g_p8)
    _, g_tap = vjp(net[tap_end:6], L, g_p5.clamp(min=0))
    return g_tap.clamp(min=0) if clamp_at_tap else g_tap


@pytest.fixture
def images():
    g = torch.Generator().manual_seed(0)
    return torch.rand(3, 3, 32, 32, dtype=torch.float64, generator=g)


def test_descriptor_on_a_users_sequential_equals_the_hand_built_gradient(images):
    net = vgg_like()
    desc = AttentionDescriptor(backbone=net, tap="2", input_size=(32, 32), mean=None, std=None, fusion="dam",
                               num_rnn=16, seed=0).double()
    assert desc.backbone.tap_shape == (8, 16, 16)
    assert desc.backbone.clamp_at_tap and desc.backbone.transitions == ("5", "8")
    assert desc.backbone_name == "Sequential.2"
    tap, grad, _fused, d = desc.parts(images)
    assert d.shape == (3, 1024) and torch.allclose(d.norm(dim=1), torch.ones(3, dtype=torch.float64))
    assert torch.allclose(tap, net[:3](images))
    ref = hand_built_gradient(net, images, clamp_at_tap=True, tap_end=3)
    assert ref.abs().max() > 0 and (ref == 0).any()
    assert torch.allclose(grad, ref, rtol=1e-10, atol=1e-14 * float(ref.abs().max()))
    # the clamps matter: without them G differs (so this test can fail)
    plain = hand_built_gradient(nn.Sequential(*net), images, clamp_at_tap=False, tap_end=3)
    assert not torch.allclose(plain, ref)


def test_tap_that_is_not_a_max_pool_output_is_not_clamped(images):
    net = vgg_like()
    hooked = HookedBackbone(net, "1", input_size=(32, 32))  # the ReLU before pool2: L is not a max-pool's output
    assert not hooked.clamp_at_tap and hooked.transitions == ("2", "5", "8")
    # hand-built: clamp at pool2, pool5, pool8; none at L
    with torch.no_grad():
        L = net[:2](images)
    g_p2 = hand_built_gradient(net, images, clamp_at_tap=True, tap_end=3)  # clamped at pool2, pool5, pool8
    _, ref = vjp(net[2], L, g_p2)  # back through pool2 to L, no clamp there
    _, grad = guided_backprop(hooked, images)
    assert torch.allclose(grad, ref, rtol=1e-10, atol=1e-14 * float(ref.abs().max()))
    unclamped_pool2 = hand_built_gradient(net, images, clamp_at_tap=False, tap_end=3)
    assert not torch.allclose(vjp(net[2], L, unclamped_pool2)[1], ref)  # the clamp at pool2 matters


def test_block_ending_in_a_max_pool_is_clamped_at_the_tap(images):
    base = vgg_like()
    net = nn.Sequential(nn.Sequential(*base[:3]), *base[3:])  # "0" is a block whose output is pool2's
    hooked = HookedBackbone(net, "0", input_size=(32, 32))
    assert hooked.clamp_at_tap and hooked.transitions == ("3", "6")
    _, grad = guided_backprop(hooked, images)
    ref = hand_built_gradient(base, images, clamp_at_tap=True, tap_end=3)
    assert torch.allclose(grad, ref, rtol=1e-10, atol=1e-14 * float(ref.abs().max()))


def test_users_module_modes_and_flags_are_left_alone(images):
    net = vgg_like().train()
    net[3].requires_grad_(False)  # the user froze one layer
    net[6].eval()  # and put one submodule in eval mode
    modes = {n: m.training for n, m in net.named_modules()}
    flags = {n: p.requires_grad for n, p in net.named_parameters()}
    desc = AttentionDescriptor(net, tap="2", input_size=(32, 32))
    desc(images)
    desc.parts(images)
    assert {n: m.training for n, m in net.named_modules()} == modes
    assert {n: p.requires_grad for n, p in net.named_parameters()} == flags
    assert all(p.grad is None for p in net.parameters())
    for m in net.modules():
        assert not m._forward_hooks and not m._forward_pre_hooks and not m._backward_hooks
    assert "backbone.module.0.weight" in desc.state_dict()


def test_batch_norm_statistics_untouched_and_batch_independent():
    torch.manual_seed(1)
    net = nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), nn.BatchNorm2d(8), nn.ReLU(), nn.MaxPool2d(2),
                        nn.Dropout(0.5), nn.Flatten(), nn.Linear(8 * 8 * 8, 5)).train()
    stats = (net[1].running_mean.clone(), net[1].running_var.clone(), int(net[1].num_batches_tracked))
    desc = AttentionDescriptor(net, tap="3", input_size=(16, 16))  # the dry run is one of the forwards
    x = torch.rand(4, 3, 20, 24)
    d = desc(x)
    for i in range(4):
        assert torch.allclose(desc(x[i:i + 1]), d[i:i + 1], atol=1e-6)
    assert torch.equal(net[1].running_mean, stats[0]) and torch.equal(net[1].running_var, stats[1])
    assert int(net[1].num_batches_tracked) == stats[2] and net.training


def test_in_place_layer_after_the_tap_and_early_stop(images):
    torch.manual_seed(0)
    net = nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), nn.ReLU(inplace=True), nn.MaxPool2d(2),
                        nn.Flatten(), nn.Linear(8 * 16 * 16, 4)).double()
    hooked = HookedBackbone(net, "0", input_size=(32, 32))  # L = the conv output, then an in-place ReLU
    x = hooked.preprocess(images)
    tap, grad = guided_backprop(hooked, images)
    assert torch.allclose(tap, net[0](x)) and (tap < 0).any()  # the in-place ReLU did not change L
    calls = []
    handle = net[4].register_forward_hook(lambda *a: calls.append(1))
    assert torch.allclose(hooked.forward_to_tap(x), tap)
    handle.remove()
    assert calls == []  # forward_to_tap stopped at the tap
    assert grad.shape == tap.shape


class Residual(nn.Module):
    def __init__(self, ch: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(ch, ch, 3, padding=1)
        self.conv2 = nn.Conv2d(ch, ch, 3, padding=1)

    def forward(self, x):
        return F.relu(x + self.conv2(F.relu(self.conv1(x))))


def test_skip_connection_around_the_tap_keeps_its_real_value(images):
    # L inside a residual block: the rest of the network also sees the block's input x. G = dS/dL with x
    # held at its real value (the hook runs the network once; nothing is recomputed from L alone).
    torch.manual_seed(0)
    net = nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), Residual(8), nn.AdaptiveAvgPool2d(1), nn.Flatten(),
                        nn.Linear(8, 6)).double()
    with torch.no_grad():
        net[4].weight.mul_(10.0)
    hooked = HookedBackbone(net, "1.conv1", input_size=(16, 16))
    assert not hooked.clamp_at_tap and hooked.transitions == ()
    tap, grad = guided_backprop(hooked, images)
    x0 = net[0](hooked.preprocess(images)).detach()
    leaf = net[1].conv1(x0).detach().requires_grad_(True)
    out = F.relu(x0 + net[1].conv2(F.relu(leaf)))
    probs = net[2:](out).softmax(1)
    (ref,) = torch.autograd.grad(0.5 * probs.pow(2).sum(), leaf)  # J^T S = d(|S|^2 / 2)/dL without clamps
    assert torch.allclose(tap, leaf) and torch.allclose(grad, ref, rtol=1e-10, atol=1e-16)


def test_explicit_transitions_for_a_functional_max_pool(images):
    class FunctionalPool(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.conv = nn.Conv2d(8, 12, 3, padding=1)

        def forward(self, x):
            return F.max_pool2d(F.relu(self.conv(x)), 2)  # invisible to hooks

    torch.manual_seed(0)
    net = nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2), FunctionalPool(),
                        nn.Flatten(), nn.Linear(12 * 8 * 8, 7)).double()
    with torch.no_grad():
        net[5].weight.mul_(20.0)
    auto = HookedBackbone(net, "2", input_size=(32, 32))
    assert auto.clamp_at_tap and auto.transitions == ()
    explicit = HookedBackbone(net, "2", input_size=(32, 32), transitions=["2", "3"])
    assert explicit.clamp_at_tap and explicit.transitions == ("3",)
    tap, grad = guided_backprop(explicit, images)
    with torch.no_grad():
        p3 = net[3](tap)
        g_p3 = (seeded_logit_gradient(net[4:](p3)) @ net[5].weight).view_as(p3).clamp(min=0)
    _, ref = vjp(net[3], tap, g_p3)
    assert torch.allclose(grad, ref.clamp(min=0), rtol=1e-10, atol=1e-16)
    _, g_auto = guided_backprop(auto, images)
    assert not torch.allclose(g_auto, grad)
    with pytest.raises(ValueError, match="no submodule 'nope'"):
        HookedBackbone(net, "2", input_size=(32, 32), transitions=["nope"])


def test_differentiable_reaches_the_users_weights_without_touching_flags(images):
    net = vgg_like().train()
    net[0].requires_grad_(False)
    desc = AttentionDescriptor(net, tap="2", input_size=(32, 32), fusion="dam", differentiable=True).double()
    desc(images).sum().backward()
    assert net[0].weight.grad is None and not net[0].weight.requires_grad
    for layer in (3, 6, 10):  # after the tap: reached through G (second order) and through L
        assert net[layer].weight.grad.abs().max() > 0
    assert net.training


@pytest.mark.parametrize(
    "make, tap, kwargs, err",
    [
        (vgg_like, "nope", {}, r"Sequential has no submodule 'nope'; its submodules: '0', '1'"),
        (vgg_like, "9", {"input_size": (32, 32)}, r"must return a \(B, C, h, w\) feature map"),
        (lambda: nn.Sequential(nn.Conv2d(3, 4, 3), nn.ReLU()), "0", {}, "must return class logits"),
        (vgg_like, "2", {"input_size": (64, 64)}, r"dry run .* on a \(1, 3, 64, 64\) image failed"),
        (lambda: nn.Sequential(nn.Conv2d(3, 3, 3, padding=1), nn.Flatten(), nn.Linear(3 * 32 * 32, 4)),
         "0", {"input_size": (32, 32), "merge": True, "num_rnn": 16}, "channels, an odd number"),
        (vgg_like, "2", {"input_size": (32, 32), "mean": (0.5, 0.5)}, "mean must be 3 finite values"),
        (vgg_like, "2", {"input_size": (0, 32)}, "input_size must be"),
    ],
)
def test_construction_errors(make, tap, kwargs, err):
    with pytest.raises(ValueError, match=err):
        AttentionDescriptor(make(), tap=tap, **kwargs)


def test_probe_size_hint_and_tap_running_twice():
    with pytest.raises(ValueError, match=r"\(1, 3, 224, 224\) image failed .*set input_size=\(H, W\)"):
        HookedBackbone(vgg_like(), "2")  # the linear head needs 32 x 32
    assert HookedBackbone(vgg_like(), "2", probe_size=(32, 32)).tap_shape == (8, 16, 16)

    class Twice(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.conv = nn.Conv2d(3, 3, 3, padding=1)
            self.fc = nn.Linear(3 * 8 * 8, 2)

        def forward(self, x):
            return self.fc(self.conv(self.conv(x)).flatten(1))

    with pytest.raises(ValueError, match="ran 2 times"):
        HookedBackbone(Twice(), "conv", input_size=(8, 8))


def test_images_of_another_size_get_a_clear_error():
    torch.manual_seed(0)
    net = nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2), nn.AdaptiveAvgPool2d(1),
                        nn.Flatten(), nn.Linear(8, 5))
    desc = AttentionDescriptor(net, tap="2")
    assert desc.backbone.tap_shape == (8, 112, 112)  # the dry run at 224 x 224
    assert desc(torch.rand(1, 3, 224, 224)).shape == (1, 5 * 8)  # no RNNs: 5 regions x 8 channels
    with pytest.raises(ValueError, match=r"tap_shape is \(8, 112, 112\).*set input_size"):
        desc(torch.rand(1, 3, 64, 64))
    fixed = AttentionDescriptor(net, tap="2", input_size=(64, 64))
    assert fixed(torch.rand(2, 3, 480, 640)).shape == (2, 5 * 8)  # resized to 64 x 64


def test_settings_that_do_not_apply_are_refused():
    lite = efficientnet_lite0(pretrained=False)
    with pytest.raises(ValueError, match="own tap and preprocessing"):
        AttentionDescriptor(lite, tap="stage6")
    with pytest.raises(ValueError, match="input_size= applies to a classifier module"):
        AttentionDescriptor("efficientnet_lite0", pretrained=False, input_size=(224, 224))
    with pytest.raises(ValueError, match="pretrained=/weights= apply to a backbone name"):
        AttentionDescriptor(vgg_like(), tap="2", pretrained=True)
    with pytest.raises(TypeError, match="lacks 'preprocess'.*tap='name.of.submodule'"):
        AttentionDescriptor(vgg_like())


def test_normalisation_settings_and_empty_batch():
    net = vgg_like().float()
    mean, std = (0.4, 0.5, 0.6), (0.2, 0.25, 0.3)
    hooked = HookedBackbone(net, "2", input_size=(32, 32), mean=mean, std=std)
    x = torch.rand(2, 3, 32, 32)
    ref = (x - torch.tensor(mean).view(1, 3, 1, 1)) / torch.tensor(std).view(1, 3, 1, 1)
    assert torch.allclose(hooked.preprocess(x), ref, atol=1e-6)
    u8 = (x * 255).round().to(torch.uint8)
    assert torch.allclose(hooked.preprocess(u8), hooked.preprocess(u8.float() / 255), atol=1e-6)
    desc = AttentionDescriptor(hooked)
    assert desc(torch.zeros(0, 3, 32, 32)).shape == (0, 5 * 8)
    assert AttentionDescriptor(hooked, num_rnn=16)(torch.zeros(0, 3, 32, 32)).shape == (0, 1024)
    assert desc.parts(torch.zeros(0, 3, 32, 32)).tap.shape == (0, 8, 16, 16)


def test_logits_that_do_not_use_the_tap():
    class Detached(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.conv = nn.Conv2d(3, 4, 3, padding=1)
            self.fc = nn.Linear(4 * 8 * 8, 3)

        def forward(self, x):
            return self.fc(self.conv(x).detach().flatten(1))

    class Unused(Detached):
        def forward(self, x):
            self.conv(x)
            return self.fc(x[:, :1].expand(-1, 4, -1, -1).flatten(1))

    for cls in (Detached, Unused):
        desc = AttentionDescriptor(cls(), tap="conv", input_size=(8, 8), fusion="dam")  # "none" reads no G
        with pytest.raises(ValueError, match="do not depend on the tap through autograd"):
            desc(torch.rand(1, 3, 8, 8))


class _FrozenFeatures(nn.Module):
    """A frozen feature extractor run under no_grad inside forward, a trainable head after it."""

    def __init__(self, cut: bool = False):
        super().__init__()
        self.cut = cut
        self.features = nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2))
        self.head = nn.Sequential(nn.Conv2d(8, 8, 3, padding=1), nn.ReLU(), nn.AdaptiveAvgPool2d(1),
                                  nn.Flatten(), nn.Linear(8, 10))

    def forward(self, x):
        with torch.no_grad():
            f = self.features(x)
        if self.cut:  # the head too under no_grad: the logits really do not depend on the tap
            with torch.no_grad():
                return self.head(f)
        return self.head(f)


@pytest.mark.parametrize("differentiable", [False, True])
def test_a_no_grad_block_inside_the_models_forward_around_the_tap(differentiable):
    # The block restores, on exit, the grad mode it found; the fast path had found "off" (it was refused:
    # "the logits do not depend on the tap"). G = dS/dL needs only the head, which runs with grad.
    torch.manual_seed(0)
    net = _FrozenFeatures()
    d = AttentionDescriptor(net, tap="features", input_size=(32, 32), differentiable=differentiable)
    L, G, _, desc = d.parts(torch.randint(0, 256, (2, 3, 48, 48), dtype=torch.uint8))
    ref = softmax_seeded_gradient(L.detach(), net.head, guided=True)  # L is a max-pool output: clamped there
    assert torch.equal(G.detach(), ref) and bool(G.abs().sum() > 0)
    cut = AttentionDescriptor(_FrozenFeatures(cut=True), tap="features", input_size=(32, 32))
    with pytest.raises(ValueError, match="do not depend on the tap"):
        cut.parts(torch.randint(0, 256, (1, 3, 48, 48), dtype=torch.uint8))
