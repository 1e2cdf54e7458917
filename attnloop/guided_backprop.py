"""Softmax-seeded partial guided backprop: the attention gradient G = dS/dL at a tap layer L (docs/method.md).

S = softmax(logits) seeds the backward (``grad_outputs = S``); negative gradients are zeroed only at the
max-pool transitions after L. With ``create_graph=True`` the clamps are switched to identities once the seeded
backward is done: autograd differentiates through them as the identity they are in the forward.
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
    """Identity forward; the backward zeroes negative gradients while ``cell[0]`` (see :func:`_clamp_scope`)."""

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
    """Clamps created inside are switched to identities on exit (the module docstring says why)."""
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
    """Identity forward (a copy of ``x``, any shape); zeroes negative gradients flowing back through it.

    Place it at the block transitions of your own network's head to get the partial guided backprop.

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
    """Context manager: every submodule of ``module`` in eval mode inside, each one's own flag restored after.

    Example:
        >>> net = nn.Sequential(nn.Linear(2, 2), nn.Dropout(0.5)).train()
        >>> net[0].eval()
        Linear(in_features=2, out_features=2, bias=True)
        >>> with eval_mode(net):
        ...     inside = [m.training for m in net.modules()]
        >>> inside, [m.training for m in net.modules()]
        ([False, False, False], [True, False, True])
    """
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
    if not isinstance(logits, Tensor) or logits.ndim != 2 or logits.shape[0] != wrt.shape[0]:
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
            the head's parameters.

    Returns:
        G with the shape of ``tap``; detached unless ``create_graph``. Batched samples do not mix.
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
    # images -> logits with at_tap(L) substituted for L (forward_split: a backbone that cannot be cut in two)
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
            # the seeded backward needs a graph from here on (undone when set_grad_enabled below exits)
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
                pair = closed(x)
                if pair is not None:
                    return pair
            with _clamp_scope():
                logits = _forward_split(backbone, x, at_tap, clamp_negative_grad)
                if "var" not in captured:
                    raise RuntimeError(f"{type(backbone).__name__} never reached its tap during the forward pass")
                if not differentiable and isinstance(logits, Tensor) and not logits.requires_grad:
                    # a no_grad block in the model's forward around the tap restored grad "off" for the
                    # head: once more with grad on throughout (a tap really cut from the logits fails below)
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
    """

    def __init__(self, backbone: nn.Module, create_graph: bool = False) -> None:
        super().__init__()
        self.backbone = backbone
        self.create_graph = bool(create_graph)

    def forward(self, images: Tensor) -> tuple[Tensor, Tensor]:
        return guided_backprop(self.backbone, images, create_graph=self.create_graph)

    def extra_repr(self) -> str:
        return f"create_graph={self.create_graph}"
