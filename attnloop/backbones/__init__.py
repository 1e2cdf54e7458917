"""CNN backbones split at a tap layer L, each with its own preprocessing and classifier head.

The protocol (``preprocess``, ``forward_to_tap``, ``forward_from_tap`` or ``forward_split``, optionally
``tap_and_seeded_gradient``): docs/your_own_cnn.md. Any other classifier becomes one with :class:`HookedBackbone`.
"""
from __future__ import annotations

import logging
from pathlib import Path

from torch import nn

from .efficientnet_lite import EfficientNetLite0, efficientnet_lite0
from .hooked import MAX_POOL_TYPES, HookedBackbone
from .preprocess import FLOAT_RANGE_TOLERANCE, check_images, prepare_images
from .vgg16 import VGG16, VGG16_TAPS, vgg16
from .weights import VGG16_FILE, WeightsNotFoundError, hub_checkpoint_dir

__all__ = [
    "BACKBONES",
    "FLOAT_RANGE_TOLERANCE",
    "MAX_POOL_TYPES",
    "VGG16",
    "VGG16_TAPS",
    "EfficientNetLite0",
    "HookedBackbone",
    "WeightsNotFoundError",
    "build_backbone",
    "check_images",
    "efficientnet_lite0",
    "prepare_images",
    "resolve_backbone_name",
    "vgg16",
]

#: Backbone name -> default tap.
BACKBONES = {"vgg16": "pool5", "efficientnet_lite0": "stage7"}
#: The name that picks one of :data:`BACKBONES` by what is installed (see :func:`resolve_backbone_name`).
AUTO = "auto"

# a child of the "attnloop" logger: a command can silence the notice (attnloop-slam --quiet) and no other warning
_log = logging.getLogger("attnloop.backbones")
_auto_notice_given = False  # the notice of "auto" without VGG16's weights: once per process


def resolve_backbone_name(name: str, pretrained: bool = True, weights: str | Path | None = None) -> str:
    """The backbone a name stands for: itself, or for ``"auto"`` the one whose weights are at hand.

    ``"auto"`` is ``"vgg16"`` when ``weights`` is given or ``vgg16-397923af.pth`` is in the torch hub
    cache, else ``"efficientnet_lite0"`` (with a one-line notice once per process when pretrained).

    Args:
        name: ``"auto"`` or one of :data:`BACKBONES`.
        pretrained: whether ImageNet weights will be loaded.
        weights: an explicit checkpoint path.

    Returns:
        one of :data:`BACKBONES`.
    """
    if name != AUTO:
        if name not in BACKBONES:
            raise ValueError(f"unknown backbone {name!r}; choose one of {[AUTO, *sorted(BACKBONES)]}")
        return name
    if weights is not None:
        return "vgg16"
    if not pretrained:
        return "efficientnet_lite0"
    cached = hub_checkpoint_dir() / VGG16_FILE
    if cached.is_file():
        return "vgg16"
    global _auto_notice_given
    if not _auto_notice_given:
        _auto_notice_given = True
        _log.warning(f"attnloop: backbone 'auto' uses EfficientNet-Lite0: the VGG16 ImageNet weights are not in "
                     f"{cached} (no download tried; backbone='vgg16' downloads them)")
    return "efficientnet_lite0"


def build_backbone(
    name: str,
    pretrained: bool = True,
    weights: str | Path | None = None,
    tap: str | None = None,
    seed: int = 0,
    input_size: tuple[int, int] | None = None,
    attend: str | None = None,
) -> nn.Module:
    """Build a backbone by name (``auto``, ``vgg16`` or ``efficientnet_lite0``), in eval mode.

    Args:
        name: the backbone name; ``auto`` resolves with :func:`resolve_backbone_name`.
        pretrained: load ImageNet weights (see :func:`vgg16` and :func:`efficientnet_lite0`).
        weights: an explicit checkpoint path.
        tap: the tap layer; the backbone's default (:data:`BACKBONES`) when None.
        seed: seed of the random weights when not pretrained.
        input_size: EfficientNet-Lite0's network input (H, W) (default 224 x 224); VGG16 takes 224 x 224 only.
        attend: EfficientNet-Lite0's stages of a joined tap where G is computed (None: all).
    """
    resolved = resolve_backbone_name(name, pretrained, weights)
    tap = BACKBONES[resolved] if tap is None else tap
    if resolved == "vgg16":
        if input_size is not None and tuple(input_size) != (224, 224):
            raise ValueError(f"VGG16's classifier takes 224 x 224 inputs, got input_size={tuple(input_size)}")
        if attend not in (None, tap):
            raise ValueError(f"attend={attend!r} applies to a joined EfficientNet-Lite tap; VGG16's tap is one layer "
                             f"({tap!r}), attended whole")
        return vgg16(pretrained=pretrained, weights=weights, tap=tap, seed=seed)
    try:
        return efficientnet_lite0(pretrained=pretrained, weights=weights, tap=tap, seed=seed, input_size=input_size,
                                  attend=attend)
    except WeightsNotFoundError as exc:
        if name != AUTO:
            raise
        raise WeightsNotFoundError(
            f"backbone 'auto' found no pretrained weights: neither VGG16's ({VGG16_FILE} in "
            f"{hub_checkpoint_dir()}) nor EfficientNet-Lite0's. {exc}") from exc
