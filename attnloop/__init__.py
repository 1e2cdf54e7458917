"""attnloop: object-aware attention guided frame association (loop closure) for RGB-D SLAM.

The paper's modules as drop-in PyTorch pieces, images -> (B, D) (:class:`AttentionDescriptor`); docs/method.md.

Example:
    >>> import torch
    >>> from attnloop import AttentionDescriptor
    >>> desc = AttentionDescriptor("efficientnet_lite0", fusion="dam", pretrained=False)
    >>> desc(torch.rand(1, 3, 480, 640)).shape
    torch.Size([1, 560])
"""
from __future__ import annotations

from .backbones import (
    VGG16,
    EfficientNetLite0,
    HookedBackbone,
    WeightsNotFoundError,
    build_backbone,
    efficientnet_lite0,
    resolve_backbone_name,
    vgg16,
)
from .descriptor import (
    AttentionDescriptor,
    DescriptorParts,
    DescriptorRecipe,
    descriptor_from_attention,
)
from .fusion import FUSION_MODES, Fusion, dam, eam, ega, fuse, gaf, minmax_normalize, no_attention
from .guided_backprop import GuidedBackprop, clamp_negative_grad, eval_mode, guided_backprop, softmax_seeded_gradient
from .rnn_pool import RandomRNNPool, merge_channels, random_rnn_pool, random_rnn_weights

__all__ = [
    "FUSION_MODES",
    "VGG16",
    "AttentionDescriptor",
    "DescriptorParts",
    "DescriptorRecipe",
    "EfficientNetLite0",
    "Fusion",
    "GuidedBackprop",
    "HookedBackbone",
    "RandomRNNPool",
    "WeightsNotFoundError",
    "build_backbone",
    "clamp_negative_grad",
    "dam",
    "descriptor_from_attention",
    "eam",
    "efficientnet_lite0",
    "ega",
    "eval_mode",
    "fuse",
    "gaf",
    "guided_backprop",
    "merge_channels",
    "minmax_normalize",
    "no_attention",
    "random_rnn_pool",
    "random_rnn_weights",
    "resolve_backbone_name",
    "softmax_seeded_gradient",
    "vgg16",
]

__version__ = "0.1.0"
