"""CNN backbones split at a tap layer L, each with its own preprocessing and classifier head.

A backbone here is an ``nn.Module`` with

- ``preprocess(images)``: (B, 3, H, W) uint8 or [0, 1] float -> the normalised network input;
- ``forward_to_tap(x)``: network input -> tap L, shape ``(B, *tap_shape)``;
- ``forward_from_tap(L, transition=None)``: L -> logits, applying ``transition`` at L and at the later
  block transitions (what the guided backprop uses to zero negative gradients there);
- ``forward(images)``: the plain classifier, images -> logits.

Any module with these methods (and a ``tap_shape`` attribute) works with
:func:`attnloop.guided_backprop.guided_backprop` and :class:`attnloop.AttentionDescriptor`.
"""
from __future__ import annotations

from pathlib import Path

from torch import nn

from .efficientnet_lite import EFFICIENTNET_LITE0_TAPS, EfficientNetLite0, efficientnet_lite0
from .preprocess import check_images, prepare_images
from .vgg16 import VGG16, VGG16_TAPS, vgg16
from .weights import WeightsNotFoundError

__all__ = [
    "BACKBONES",
    "EFFICIENTNET_LITE0_TAPS",
    "VGG16",
    "VGG16_TAPS",
    "EfficientNetLite0",
    "WeightsNotFoundError",
    "build_backbone",
    "check_images",
    "efficientnet_lite0",
    "prepare_images",
    "vgg16",
]

#: Backbone name -> default tap.
BACKBONES = {"vgg16": "pool5", "efficientnet_lite0": "stage7"}


def build_backbone(
    name: str,
    pretrained: bool = True,
    weights: str | Path | None = None,
    tap: str | None = None,
    seed: int = 0,
) -> nn.Module:
    """Build a backbone by name (``vgg16`` or ``efficientnet_lite0``), in eval mode.

    Args:
        name: the backbone name.
        pretrained: load ImageNet weights (see :func:`vgg16` and :func:`efficientnet_lite0`).
        weights: an explicit checkpoint path.
        tap: the tap layer; the backbone's default (:data:`BACKBONES`) when None.
        seed: seed of the random weights when not pretrained.

    Example:
        >>> build_backbone("vgg16", pretrained=False).tap_shape
        (512, 7, 7)
    """
    if name not in BACKBONES:
        raise ValueError(f"unknown backbone {name!r}; choose one of {sorted(BACKBONES)}")
    tap = BACKBONES[name] if tap is None else tap
    if name == "vgg16":
        return vgg16(pretrained=pretrained, weights=weights, tap=tap, seed=seed)
    return efficientnet_lite0(pretrained=pretrained, weights=weights, tap=tap, seed=seed)
