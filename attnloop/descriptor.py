"""The attention-guided CNN descriptor: backbone -> guided attention -> fusion -> random RNN pooling -> L2.

For a batch of images:

1. L, G = the tap activations and the softmax-seeded partial guided gradient
   (:func:`attnloop.guided_backprop.guided_backprop`);
2. F = fusion(L, G), one of ``none``, ``dam``, ``eam``, ``gaf``, ``ega`` (:mod:`attnloop.fusion`), with
   G scaled to max |G| = 1 per sample first (the fusions are invariant to that scale; it keeps a tiny G,
   e.g. from a flat softmax, above the constant-map threshold of the min-max normalisation);
3. F is L2-normalised per sample and scaled to norm ``pool_scale`` (10 by default; None skips it);
4. d = random RNN pooling of F (:mod:`attnloop.rnn_pool`), (B, num_rnn * 64);
5. d is L2-normalised (``normalize=True``), so the dot product of two descriptors is their cosine.

Step 3 is ours, not the paper's: it makes the descriptor independent of the fused map's overall scale
(which differs between fusion modes and frames) and sets the operating point of the RNNs' tanh. With
raw features at EfficientNet's stage7 the pre-activations W_r x have a standard deviation of 5 to 17
(median over frames, depending on the fusion), so the tanh saturates and the 1024 dims degrade to a
1024-bit sign hash; at norm 10 it is 0.29 and the pooling is close to a random projection. On the
7-Scenes redkitchen revisits this raises the loop-closure margins and narrows their spread over RNN
seeds (docs/attention.md).
"""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from .backbones import build_backbone
from .backbones.preprocess import check_images
from .fusion import FUSION_MODES, Fusion, fuse
from .guided_backprop import guided_backprop
from .rnn_pool import RandomRNNPool, random_rnn_pool

__all__ = [
    "AttentionDescriptor",
    "DescriptorParts",
    "attention_descriptor",
    "attention_descriptor_parts",
    "descriptor_from_attention",
]


class DescriptorParts(NamedTuple):
    """Every intermediate of one descriptor computation, for inspection.

    Attributes:
        tap: the tap activations L, :math:`(B, C, h, w)`.
        grad: the guided gradient G = dS/dL, :math:`(B, C, h, w)`.
        fused: fusion(L, G / max|G|), :math:`(B, C, h, w)` (before the scaling of the pooling input).
        descriptor: the descriptor, :math:`(B, D)`.
    """

    tap: torch.Tensor
    grad: torch.Tensor
    fused: torch.Tensor
    descriptor: torch.Tensor


def _unit_scale(grad: torch.Tensor) -> torch.Tensor:
    # Every fusion uses G only through min-max normalisations, which ignore a positive per-sample
    # scale, but minmax_normalize treats ranges below 1e-12 as constant. G = J^T S can be that small
    # (a flat softmax: random weights, or an image the classifier finds meaningless), so G is brought
    # to max |G| = 1 per sample first. An all-zero G stays zero.
    peak = grad.detach().abs().amax(dim=tuple(range(1, grad.ndim)), keepdim=True)
    return grad / peak.clamp_min(torch.finfo(grad.dtype).tiny)


def _scale_to_norm(x: torch.Tensor, norm: float) -> torch.Tensor:
    # Per-sample L2 normalisation to `norm`; an all-zero sample stays zero (no NaN).
    flat = x.reshape(x.shape[0], -1)
    return (F.normalize(flat, dim=1) * norm).reshape(x.shape)


def descriptor_from_attention(
    tap: torch.Tensor,
    grad: torch.Tensor,
    rnn_weights: torch.Tensor,
    fusion: str = "dam",
    normalize: bool = True,
    pool_scale: float | None = 10.0,
    merge: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Steps 2-5 of the descriptor: fuse (L, G), scale, random RNN pooling, L2.

    Useful to try several fusion modes on one (L, G) without running the backbone again.

    Args:
        tap: the tap activations L, :math:`(B, C, h, w)`.
        grad: the guided gradient G, :math:`(B, C, h, w)`.
        rnn_weights: :math:`(R, O, I)` random RNN weights with ``I = C/2 * h * w`` (``C * h * w``
            without merge).
        fusion: ``none``, ``dam``, ``eam``, ``gaf`` or ``ega``.
        normalize: L2-normalise the descriptor.
        pool_scale: L2 norm the fused map is scaled to before the pooling; None feeds it raw (the paper).
        merge: average channel c with c + C/2 before the pooling (the paper's merge).

    Returns:
        (fused :math:`(B, C, h, w)`, descriptor :math:`(B, R \\cdot O)`).

    Example:
        >>> from attnloop.rnn_pool import random_rnn_weights
        >>> L, G = torch.rand(2, 512, 7, 7), torch.randn(2, 512, 7, 7)
        >>> fused, d = descriptor_from_attention(L, G, random_rnn_weights(16, 256 * 49, 64), "gaf")
        >>> fused.shape, d.shape
        (torch.Size([2, 512, 7, 7]), torch.Size([2, 1024]))
    """
    fused = fuse(tap, _unit_scale(grad), fusion)
    pooled_in = fused if pool_scale is None else _scale_to_norm(fused, float(pool_scale))
    desc = random_rnn_pool(pooled_in, rnn_weights, merge=merge)
    if normalize:
        desc = F.normalize(desc, dim=1)
    return fused, desc


def attention_descriptor_parts(
    images: torch.Tensor,
    backbone: nn.Module,
    rnn_weights: torch.Tensor,
    fusion: str = "dam",
    normalize: bool = True,
    pool_scale: float | None = 10.0,
    merge: bool = True,
) -> DescriptorParts:
    """Compute the descriptor and keep every intermediate (L, G, fused, descriptor).

    Args:
        images: :math:`(B, 3, H, W)` uint8 in [0, 255] or float in [0, 1], on the backbone's device.
        backbone: a backbone of :mod:`attnloop.backbones` (eval mode).
        rnn_weights: :math:`(R, O, I)` random RNN weights (:func:`attnloop.rnn_pool.random_rnn_weights`)
            with ``I = C/2 * h * w`` for the backbone's tap shape (C, h, w) (``C * h * w`` without merge).
        fusion: ``none``, ``dam``, ``eam``, ``gaf`` or ``ega``.
        normalize: L2-normalise the descriptor.
        pool_scale: L2 norm the fused map is scaled to before the pooling; None feeds it raw (the paper).
        merge: average channel c with c + C/2 before the pooling (the paper's merge).

    Returns:
        :class:`DescriptorParts` with the descriptor of shape :math:`(B, R \\cdot O)`.
    """
    check_images(images)
    tap, grad = guided_backprop(backbone, images)
    fused, desc = descriptor_from_attention(tap, grad, rnn_weights, fusion, normalize, pool_scale, merge)
    return DescriptorParts(tap, grad, fused, desc)


def attention_descriptor(
    images: torch.Tensor,
    backbone: nn.Module,
    rnn_weights: torch.Tensor,
    fusion: str = "dam",
    normalize: bool = True,
    pool_scale: float | None = 10.0,
    merge: bool = True,
) -> torch.Tensor:
    """Attention-guided descriptor of a batch of images (see :func:`attention_descriptor_parts`).

    Returns:
        :math:`(B, R \\cdot O)` descriptors, unit L2 norm when ``normalize``.

    Example:
        >>> from attnloop.backbones import efficientnet_lite0
        >>> from attnloop.rnn_pool import random_rnn_weights
        >>> net = efficientnet_lite0(pretrained=False)
        >>> w = random_rnn_weights(16, 160 * 7 * 7, 64, seed=0)
        >>> attention_descriptor(torch.rand(2, 3, 96, 128), net, w, fusion="ega").shape
        torch.Size([2, 1024])
    """
    return attention_descriptor_parts(images, backbone, rnn_weights, fusion, normalize, pool_scale, merge).descriptor


class AttentionDescriptor(nn.Module):
    """Images -> attention-guided CNN descriptors, as a drop-in ``nn.Module``.

    The backbone is frozen (no parameter requires grad) and always in eval mode, even after
    ``.train()``: the descriptor is a fixed feature extractor, not differentiable w.r.t. the images.
    It computes its own gradients internally, so it can be called under ``torch.no_grad()`` or
    ``torch.inference_mode()``.

    Args:
        backbone: ``"vgg16"`` (the paper's), ``"efficientnet_lite0"`` (weights from a pip package,
            works offline) or a backbone module of :mod:`attnloop.backbones`.
        fusion: ``"none"``, ``"dam"``, ``"eam"``, ``"gaf"`` or ``"ega"``.
        num_rnn: number of random RNNs (the descriptor has ``num_rnn * out_features`` dims).
        seed: seed of the RNN weights, and of the backbone weights when ``pretrained`` is False.
        pretrained: load ImageNet weights; False gives seeded random weights without any file.
        weights: explicit checkpoint path for the backbone.
        normalize: L2-normalise the descriptors.
        tap: the backbone's tap layer (default: ``pool5`` for VGG16, ``stage7`` for EfficientNet-Lite0).
        out_features: output size of each RNN.
        pool_scale: L2 norm of the fused map fed to the RNNs (None: raw, as in the paper).
        merge: average channel c with c + C/2 before the pooling.

    Shape:
        - images: :math:`(B, 3, H, W)`, uint8 in [0, 255] or float in [0, 1], any H and W
        - output: :math:`(B, \\text{num\\_rnn} \\cdot \\text{out\\_features})`

    Example:
        >>> desc = AttentionDescriptor("efficientnet_lite0", fusion="dam", pretrained=False)
        >>> with torch.no_grad():
        ...     d = desc(torch.randint(0, 256, (2, 3, 240, 320), dtype=torch.uint8))
        >>> d.shape
        torch.Size([2, 1024])
    """

    def __init__(
        self,
        backbone: str | nn.Module = "vgg16",
        fusion: str = "dam",
        num_rnn: int = 16,
        seed: int = 0,
        pretrained: bool = True,
        weights: str | Path | None = None,
        normalize: bool = True,
        tap: str | None = None,
        out_features: int = 64,
        pool_scale: float | None = 10.0,
        merge: bool = True,
    ) -> None:
        super().__init__()
        if isinstance(backbone, str):
            self.backbone_name = backbone
            net = build_backbone(backbone, pretrained=pretrained, weights=weights, tap=tap, seed=seed)
        elif isinstance(backbone, nn.Module):
            for attr in ("preprocess", "forward_to_tap", "forward_from_tap", "tap_shape"):
                if not hasattr(backbone, attr):
                    raise TypeError(f"backbone module {type(backbone).__name__} lacks '{attr}' (see attnloop.backbones)")
            self.backbone_name = type(backbone).__name__
            net = backbone
        else:
            raise TypeError(f"backbone must be a name or an nn.Module, got {type(backbone).__name__}")
        if fusion not in FUSION_MODES:
            raise ValueError(f"unknown fusion {fusion!r}; choose one of {FUSION_MODES}")
        if pool_scale is not None and not pool_scale > 0:
            raise ValueError(f"pool_scale must be positive or None, got {pool_scale}")
        self.backbone = net.eval().requires_grad_(False)
        self.fusion = Fusion(fusion)
        channels, height, width = self.backbone.tap_shape
        self.pool = RandomRNNPool(channels, (height, width), num_rnn, out_features, seed=seed, merge=merge)
        self.normalize = bool(normalize)
        self.pool_scale = None if pool_scale is None else float(pool_scale)

    @property
    def out_dim(self) -> int:
        """Size of a descriptor, ``num_rnn * out_features``."""
        return self.pool.out_dim

    def train(self, mode: bool = True) -> AttentionDescriptor:
        """Set the training flag; the frozen backbone stays in eval mode (batch-norm, dropout)."""
        super().train(mode)
        self.backbone.eval()
        return self

    def _check_device(self, images: torch.Tensor) -> None:
        param = next(self.backbone.parameters(), None)
        if param is not None and images.device != param.device:
            raise ValueError(
                f"images are on {images.device} but the descriptor is on {param.device}; move one of them "
                "(e.g. descriptor.to(images.device))"
            )

    def parts(self, images: torch.Tensor) -> DescriptorParts:
        """Descriptor with its intermediates (L, G, fused) for inspection; see :class:`DescriptorParts`.

        Args:
            images: :math:`(B, 3, H, W)` uint8 or [0, 1] float.
        """
        check_images(images)
        self._check_device(images)
        if images.shape[0] == 0:
            shape = (0, *self.backbone.tap_shape)
            dtype = self.pool.weights.dtype
            empty = images.new_zeros(shape, dtype=dtype)
            return DescriptorParts(empty, empty, empty, images.new_zeros((0, self.out_dim), dtype=dtype))
        return attention_descriptor_parts(
            images, self.backbone, self.pool.weights, self.fusion.mode, self.normalize, self.pool_scale,
            self.pool.merge,
        )

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.parts(images).descriptor

    def from_attention(self, tap: torch.Tensor, grad: torch.Tensor, fusion: str | None = None) -> torch.Tensor:
        """Descriptor of given (L, G), e.g. to compare fusion modes on one backbone pass.

        Args:
            tap: the tap activations L, :math:`(B, C, h, w)` of this backbone's tap shape.
            grad: the guided gradient G, same shape.
            fusion: a fusion mode; this module's own when None.

        Returns:
            :math:`(B, D)` descriptors.
        """
        if tap.ndim != 4 or tuple(tap.shape[1:]) != tuple(self.backbone.tap_shape):
            raise ValueError(f"tap must have shape (B, {', '.join(map(str, self.backbone.tap_shape))}), "
                             f"got {tuple(tap.shape)}")
        mode = self.fusion.mode if fusion is None else fusion
        return descriptor_from_attention(
            tap, grad, self.pool.weights, mode, self.normalize, self.pool_scale, self.pool.merge
        )[1]

    def extra_repr(self) -> str:
        return f"backbone={self.backbone_name!r}, normalize={self.normalize}, pool_scale={self.pool_scale}"
