"""Softmax-seeded partial guided backprop: the attention gradient G = dS/dL at a tap layer L.

Following the forward-backward saliency of Imamoglu et al. (ICIP 2017) as used by Caglayan et al.:

1. forward the image to the tap L and on through the rest of the network to the logits z;
2. S = softmax(z); the backward pass is seeded with S's own values (``grad_outputs = S.detach()``), so
   G = J^T S where J = dS/dL, i.e. G = sum_k S_k dS_k/dL;
3. on the way back the gradient's negative entries are zeroed only at the max-pool transitions between
   blocks (for VGG16 tapped at pool5: at pool5 itself; tapped at pool4: at pool5 and pool4), plain
   backprop everywhere else. EfficientNet has no max-pool, so there G is the plain seeded gradient.

Only the input gradient w.r.t. L is computed (:func:`torch.autograd.grad`), the part of the network
below L runs without autograd, nothing (``.grad``, hooks, modes) is left on the model, and it works
under :func:`torch.no_grad` or :func:`torch.inference_mode` of the caller.
"""
from __future__ import annotations

from typing import Callable

import torch
from torch import nn

__all__ = ["GuidedBackprop", "clamp_negative_grad", "guided_backprop", "softmax_seeded_gradient"]


class _ClampNegativeGrad(torch.autograd.Function):
    """Identity forward; the backward zeroes the negative entries of the incoming gradient."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        return x.clone()

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        return grad.clamp(min=0)


def clamp_negative_grad(x: torch.Tensor) -> torch.Tensor:
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
    return _ClampNegativeGrad.apply(x)


def softmax_seeded_gradient(
    tap: torch.Tensor, head: Callable[[torch.Tensor], torch.Tensor], guided: bool = True
) -> torch.Tensor:
    """G = dS/dL seeded with S: the backward of S = softmax(head(L)) with ``grad_outputs = S``.

    Args:
        tap: the tap activations L, :math:`(B, C, H, W)` (any shape with a batch dimension first).
        head: maps L to logits :math:`(B, K)`. With the transition clamps (see
            :func:`clamp_negative_grad`) inside it, this is the partial guided backprop.
        guided: also zero the negative gradient at L itself (right when L is a max-pool output).

    Returns:
        G with the shape of ``tap``, detached; batched samples do not mix.

    Example:
        >>> head = nn.Sequential(nn.Flatten(), nn.Linear(8 * 2 * 2, 5))
        >>> softmax_seeded_gradient(torch.rand(3, 8, 2, 2), head).shape
        torch.Size([3, 8, 2, 2])
    """
    if tap.ndim < 2:
        raise ValueError(f"tap must have a batch dimension, got shape {tuple(tap.shape)}")
    if tap.shape[0] == 0:
        return torch.zeros_like(tap)
    with torch.inference_mode(False), torch.enable_grad():
        leaf = tap.detach()
        if leaf.is_inference():
            leaf = leaf.clone()  # an inference tensor cannot enter an autograd graph
        leaf.requires_grad_(True)
        x = clamp_negative_grad(leaf) if guided else leaf
        logits = head(x)
        if logits.ndim != 2 or logits.shape[0] != tap.shape[0]:
            raise ValueError(f"head must return logits (B, K) with B={tap.shape[0]}, got {tuple(logits.shape)}")
        probs = torch.softmax(logits, dim=1)
        (grad,) = torch.autograd.grad(probs, leaf, grad_outputs=probs.detach())
    return grad


def guided_backprop(backbone: nn.Module, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Tap activations L and the softmax-seeded partial guided gradient G = dS/dL for a batch of images.

    Args:
        backbone: a backbone of :mod:`attnloop.backbones` (or any module with ``preprocess``,
            ``forward_to_tap`` and ``forward_from_tap(L, transition)``), normally in eval mode.
        images: :math:`(B, 3, H, W)` uint8 in [0, 255] or float in [0, 1].

    Returns:
        (L, G), both :math:`(B, C, h, w)` (the backbone's ``tap_shape``), detached.

    Example:
        >>> from attnloop.backbones import efficientnet_lite0
        >>> net = efficientnet_lite0(pretrained=False)
        >>> L, G = guided_backprop(net, torch.rand(2, 3, 120, 160))
        >>> L.shape, G.shape
        (torch.Size([2, 320, 7, 7]), torch.Size([2, 320, 7, 7]))
    """
    with torch.inference_mode(False):
        if images.is_inference():
            images = images.clone()
        with torch.no_grad():
            tap = backbone.forward_to_tap(backbone.preprocess(images))
        # The backbone applies the transition clamp at L itself when L is a max-pool output (VGG16);
        # guided=False here avoids clamping twice.
        grad = softmax_seeded_gradient(
            tap, lambda t: backbone.forward_from_tap(t, transition=clamp_negative_grad), guided=False
        )
    return tap, grad


class GuidedBackprop(nn.Module):
    """Module wrapper of :func:`guided_backprop` around a backbone.

    Args:
        backbone: a backbone of :mod:`attnloop.backbones`.

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

    def __init__(self, backbone: nn.Module) -> None:
        super().__init__()
        self.backbone = backbone

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return guided_backprop(self.backbone, images)
