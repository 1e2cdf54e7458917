"""Softmax-seeded partial guided backprop: the attention gradient G = dS/dL at a tap layer L.

Following the forward-backward saliency of Imamoglu et al. (ICIP 2017) as used by Caglayan et al.:

1. forward the image to the tap L and on through the rest of the network to the logits z;
2. S = softmax(z); the backward pass is seeded with S's own values (``grad_outputs = S``), so
   G = J^T S where J = dS/dL, i.e. G = sum_k S_k dS_k/dL;
3. on the way back the gradient's negative entries are zeroed only at the max-pool transitions between
   blocks (for VGG16 tapped at pool5: at pool5 itself; tapped at pool4: at pool5 and pool4), plain
   backprop everywhere else. EfficientNet has no max-pool, so there G is the plain seeded gradient.

Two modes:

- ``create_graph=False`` (the default, the fast one): only the input gradient w.r.t. L is computed
  (:func:`torch.autograd.grad`), the part of the network below L runs without autograd, and (L, G)
  come back detached. A backbone whose head after L has a closed-form seeded backward gives (L, G)
  itself, with no autograd at all (``tap_and_seeded_gradient``; EfficientNet-Lite with G at its last
  stage, the default descriptor's case: the same G, tested against autograd in float64).
- ``create_graph=True``: the forward below L keeps its graph and the seeded backward is recorded
  (``create_graph``, with the seed S itself differentiated), so L and G are differentiable functions
  of the images and of the backbone's weights; G's derivative is a second-order one through the head.
  Under the caller's :func:`torch.no_grad` or :func:`torch.inference_mode` there is no graph to
  build, and the results are the detached ones of the default mode.

The clamps in the differentiable mode: G = B(L)^T S(L), B the backward with the clamps. Autograd
differentiates G through the recorded backward (where a clamp ``max(g, 0)`` has derivative
``1[g > 0]``) and through the forward graph (S depends on L through the logits), where the clamp's op
is the identity and must be differentiated as one. So once the seeded backward is done, the clamps
of that forward pass are switched to identities (:func:`clamp_negative_grad` outside such a
computation always clamps). Measured against central finite differences in float64 the directional
derivatives agree to ~1e-7 relative (tests/attnloop/test_descriptor_autograd.py); with the clamps left on,
autograd is off by 10-100 % for the fusions that use G.

Either way nothing (``.grad``, hooks, requires_grad flags) is left on the model, and the backbone runs in
eval mode during the computation (batch-norm running statistics, no dropout) so that a result never
depends on the rest of its batch; each submodule's training flag is restored afterwards.
"""
from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Callable

import torch
from torch import nn

__all__ = ["GuidedBackprop", "clamp_negative_grad", "eval_mode", "guided_backprop", "softmax_seeded_gradient"]

Tensor = torch.Tensor


class _ClampNegativeGrad(torch.autograd.Function):
    """Identity forward; the backward zeroes the negative entries of the incoming gradient.

    ``cell[0]`` switches the clamp: after the seeded backward of a differentiable computation the
    clamps are switched off (:func:`_clamp_scope`), so that a later backward through the *forward*
    pass sees this op as what it is, the identity. The clamp recorded inside the seeded backward
    (``create_graph``) stays: its derivative is ``1[g > 0]``.
    """

    @staticmethod
    def forward(ctx, x: Tensor, cell: list) -> Tensor:  # type: ignore[override]
        ctx.cell = cell
        return x.clone()

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        return (grad.clamp(min=0) if ctx.cell[0] else grad), None


_scopes = threading.local()


@contextmanager
def _clamp_scope() -> Iterator[None]:
    """Clamps created inside are switched to identities on exit (see :class:`_ClampNegativeGrad`).

    Why: G = B(L)^T S(L), with B the clamped backward. Differentiating G by autograd goes back through
    the forward graph too (S depends on L through the logits), and there the true derivative of an
    identity is the identity, not the clamp.
    """
    stack = getattr(_scopes, "stack", None)
    if stack is None:
        stack = _scopes.stack = []
    cells: list[list] = []
    stack.append(cells)
    try:
        yield
    finally:
        stack.pop()
        for cell in cells:
            cell[0] = False


def clamp_negative_grad(x: Tensor) -> Tensor:
    """Identity in the forward pass; zeroes negative gradients flowing back through this point.

    Place it at the block transitions of your own network's head to get the partial guided backprop.

    Args:
        x: any tensor.

    Returns:
        a tensor equal to ``x`` (a copy, so later in-place ops are safe).

    Example:
        >>> x = torch.tensor([1.0, -2.0], requires_grad=True)
        >>> (g,) = torch.autograd.grad(clamp_negative_grad(x), x, torch.tensor([-1.0, 3.0]))
        >>> g.tolist()
        [0.0, 3.0]
    """
    cell = [True]
    stack = getattr(_scopes, "stack", None)
    if stack:
        stack[-1].append(cell)
    return _ClampNegativeGrad.apply(x, cell)


@contextmanager
def eval_mode(module: nn.Module) -> Iterator[nn.Module]:
    """Context manager: every submodule of ``module`` in eval mode inside, its own flag restored after.

    The flags are set and restored one submodule at a time (not through ``module.train()``), so a
    model whose submodules were in mixed modes gets exactly those modes back, even after an exception.

    Args:
        module: any module.

    Example:
        >>> net = nn.Sequential(nn.Linear(2, 2), nn.Dropout(0.5)).train()
        >>> net[0].eval()
        Linear(in_features=2, out_features=2, bias=True)
        >>> with eval_mode(net):
        ...     inside = [m.training for m in net.modules()]
        >>> inside, [m.training for m in net.modules()]
        ([False, False, False], [True, False, True])
    """
    # Only the submodules in training mode are switched (and switched back): a backbone already in eval
    # mode, the descriptor's usual case, costs no attribute writes (Module.__setattr__ is slow, and a
    # backbone has ~100 submodules: it showed in profiles of batch-1 descriptor calls).
    training = [m for m in module.modules() if m.training]
    try:
        for m in training:
            m.training = False
        yield module
    finally:
        for m in training:
            m.training = True


def _seeded_backward(logits: Tensor, wrt: Tensor, create_graph: bool) -> Tensor:
    """G = (dS/d wrt)^T S with S = softmax(logits); the one place the seeded backward is written."""
    if logits.ndim != 2 or logits.shape[0] != wrt.shape[0]:
        raise ValueError(
            f"the network after the tap must return logits (B, K) with B={wrt.shape[0]}, got "
            f"{tuple(logits.shape) if isinstance(logits, Tensor) else type(logits).__name__}"
        )
    unused = ("the logits do not depend on the tap through autograd: is its output unused, detached or run "
              "under no_grad on the way to the logits?")
    if not logits.requires_grad:
        raise ValueError(unused)
    probs = torch.softmax(logits, dim=1)
    # Differentiable mode keeps the seed in the graph: G(L) = J(L)^T S(L) depends on L through both.
    seed = probs if create_graph else probs.detach()
    (grad,) = torch.autograd.grad(probs, wrt, grad_outputs=seed, create_graph=create_graph, allow_unused=True)
    if grad is None:
        raise ValueError(unused)
    return grad


def _differentiable(create_graph: bool) -> bool:
    # Under the caller's no_grad / inference_mode there is no graph to build: the fast path gives the
    # same values.
    return bool(create_graph) and torch.is_grad_enabled() and not torch.is_inference_mode_enabled()


def softmax_seeded_gradient(
    tap: Tensor, head: Callable[[Tensor], Tensor], guided: bool = True, create_graph: bool = False
) -> Tensor:
    """G = dS/dL seeded with S: the backward of S = softmax(head(L)) with ``grad_outputs = S``.

    Args:
        tap: the tap activations L, :math:`(B, C, H, W)` (any shape with a batch dimension first).
        head: maps L to logits :math:`(B, K)`. With the transition clamps (see
            :func:`clamp_negative_grad`) inside it, this is the partial guided backprop.
        guided: also zero the negative gradient at L itself (right when L is a max-pool output).
        create_graph: return G as a differentiable function of ``tap`` (when it requires grad) and of
            the head's parameters; see the module docstring.

    Returns:
        G with the shape of ``tap``; detached unless ``create_graph``. Batched samples do not mix.

    Example:
        >>> head = nn.Sequential(nn.Flatten(), nn.Linear(8 * 2 * 2, 5))
        >>> softmax_seeded_gradient(torch.rand(3, 8, 2, 2), head).shape
        torch.Size([3, 8, 2, 2])
    """
    if not isinstance(tap, Tensor):
        raise TypeError(f"tap must be a torch.Tensor, got {type(tap).__name__}")
    if tap.ndim < 2:
        raise ValueError(f"tap must have a batch dimension, got shape {tuple(tap.shape)}")
    differentiable = _differentiable(create_graph)
    if tap.shape[0] == 0:
        return torch.zeros_like(tap if differentiable else tap.detach())
    with torch.inference_mode(False), torch.enable_grad():
        if differentiable and tap.requires_grad:
            leaf = tap
        else:
            leaf = tap.detach()
            if leaf.is_inference():
                leaf = leaf.clone()  # an inference tensor cannot enter an autograd graph
            leaf.requires_grad_(True)
        with _clamp_scope():
            x = clamp_negative_grad(leaf) if guided else leaf
            return _seeded_backward(head(x), leaf, differentiable)


def _forward_split(backbone: nn.Module, x: Tensor, at_tap: Callable[[Tensor], Tensor],
                   transition: Callable[[Tensor], Tensor]) -> Tensor:
    # One forward pass, images -> logits, with at_tap(L) substituted for L. A backbone that cannot be
    # split into two calls (a hooked generic module) provides forward_split itself.
    split = getattr(backbone, "forward_split", None)
    if callable(split):
        return split(x, at_tap, transition)
    return backbone.forward_from_tap(at_tap(backbone.forward_to_tap(x)), transition=transition)


def guided_backprop(backbone: nn.Module, images: Tensor, create_graph: bool = False) -> tuple[Tensor, Tensor]:
    """Tap activations L and the softmax-seeded partial guided gradient G = dS/dL for a batch of images.

    Args:
        backbone: a backbone of :mod:`attnloop.backbones` (or any module with ``preprocess``,
            ``forward_to_tap`` and ``forward_from_tap(L, transition)``, or ``forward_split``; see
            :mod:`attnloop.backbones`). It runs in eval mode here whatever its own mode (restored after).
        images: :math:`(B, 3, H, W)` uint8 in [0, 255] or float in [0, 1].
        create_graph: keep the graph: L and G differentiable w.r.t. the images (when they require
            grad) and the backbone's weights (those that require grad).

    Returns:
        (L, G), both :math:`(B, C, h, w)` (the backbone's ``tap_shape``); detached unless ``create_graph``.

    Example:
        >>> from attnloop.backbones import efficientnet_lite0
        >>> net = efficientnet_lite0(pretrained=False)
        >>> L, G = guided_backprop(net, torch.rand(2, 3, 120, 160))
        >>> L.shape, G.shape
        (torch.Size([2, 320, 7, 7]), torch.Size([2, 320, 7, 7]))
    """
    if not isinstance(images, Tensor):
        raise TypeError(f"images must be a torch.Tensor, got {type(images).__name__}")
    differentiable = _differentiable(create_graph)
    captured: dict[str, Tensor] = {}

    def at_tap(tap: Tensor) -> Tensor:
        captured["tap"] = tap
        if differentiable and tap.requires_grad:
            var = tap
        else:
            # Below L no graph was recorded; from here on the seeded backward needs one. The grad mode
            # set here is undone when the set_grad_enabled block below exits.
            torch.set_grad_enabled(True)
            var = tap.detach().requires_grad_(True)
        captured["var"] = var
        return var

    with torch.inference_mode(False), eval_mode(backbone):
        if images.is_inference():
            images = images.clone()
        with torch.set_grad_enabled(differentiable):
            x = backbone.preprocess(images)
            if x.shape[0] == 0:
                tap = backbone.forward_to_tap(x)
                return tap, torch.zeros_like(tap)
            closed = getattr(backbone, "tap_and_seeded_gradient", None)
            if not differentiable and callable(closed):
                # The backbone's closed-form (L, G), where it has one: the same G without a graph.
                pair = closed(x)
                if pair is not None:
                    return pair
            with _clamp_scope():
                # The backbone applies the transition clamp at L itself when L is a max-pool output (VGG16).
                logits = _forward_split(backbone, x, at_tap, clamp_negative_grad)
                if "var" not in captured:
                    raise RuntimeError(f"{type(backbone).__name__} never reached its tap during the forward pass")
                if not differentiable and isinstance(logits, Tensor) and not logits.requires_grad:
                    # A no_grad block inside the model's own forward that holds the tap (a frozen feature
                    # extractor) restores, when it exits, the grad mode it found: this path's "off", so the
                    # head ran without a graph. Once more with grad on throughout (the frozen part records
                    # none anyway); a tap that is really cut from the logits still fails below.
                    captured.clear()
                    with torch.enable_grad():
                        logits = _forward_split(backbone, x, at_tap, clamp_negative_grad)
                with torch.enable_grad():  # the softmax of the seed is recorded whatever mode the forward left
                    grad = _seeded_backward(logits, captured["var"], differentiable)
    tap = captured["tap"]
    return (tap, grad) if differentiable else (tap.detach(), grad)


class GuidedBackprop(nn.Module):
    """Module wrapper of :func:`guided_backprop` around a backbone.

    Args:
        backbone: a backbone of :mod:`attnloop.backbones`.
        create_graph: return (L, G) differentiable w.r.t. the images and the backbone's weights.

    Shape:
        - images: :math:`(B, 3, H, W)` uint8 or [0, 1] float
        - output: a tuple (L, G), each :math:`(B, C, h, w)`

    Example:
        >>> from attnloop.backbones import vgg16
        >>> gbp = GuidedBackprop(vgg16(pretrained=False))
        >>> L, G = gbp(torch.rand(1, 3, 64, 64))
        >>> G.shape
        torch.Size([1, 512, 7, 7])
    """

    def __init__(self, backbone: nn.Module, create_graph: bool = False) -> None:
        super().__init__()
        self.backbone = backbone
        self.create_graph = bool(create_graph)

    def forward(self, images: Tensor) -> tuple[Tensor, Tensor]:
        return guided_backprop(self.backbone, images, create_graph=self.create_graph)

    def extra_repr(self) -> str:
        return f"create_graph={self.create_graph}"
