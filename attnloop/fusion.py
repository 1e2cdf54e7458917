"""Fusion of a CNN layer ``L`` with its attention map ``G`` (the paper's DAM, EAM, GAF, EGA).

``G`` is the guided gradient of the softmax output with respect to ``L`` (same shape as ``L``). The
operators rescale ``L`` by a normalised version of ``G``:

* ``none``: ``L``, no attention (the paper's Table 1 baseline, Guclu et al. 2019, is another descriptor:
  no attention and no merge of channel pairs before the RNNs, :mod:`attnloop.presets` ``guclu2019``);
* ``dam`` (direct attention map): ``L * N(G)``, ``N`` over ``(C, H, W)`` of each sample;
* ``eam`` (exponential attention map): ``L * exp(N(G))``;
* ``gaf`` (global attention fusion): ``L * N(sum_c N(G_c))``, the inner ``N`` per channel map over
  ``(H, W)``, the outer ``N`` over ``(H, W)`` of the channel sum, broadcast over the channels;
* ``ega`` (exponential global attention): ``L * exp(N(sum_c N(G_c)))``.

The inner ``N`` per channel is our reading of the paper's ``N(sum_i N(G_ij))``, whose notation does not say
over what the inner normalisation runs. The other reading, one inner ``N`` over the whole ``(C, H, W)`` of
each sample (as DAM's), makes it an affine map shared by every channel, which the outer ``N`` removes:
GAF would then be ``L * N(sum_c G_c)`` and EGA ``L * exp(N(sum_c G_c))``.

``N`` is a per-sample min-max normalisation to ``[0, 1]`` (:func:`minmax_normalize`); a constant map
normalises to zeros (never NaN), so with a flat attention map DAM/GAF give zeros and EAM/EGA give ``L``;
a NaN in ``G`` makes its whole normalised slice NaN (it is never hidden as a zero map).
Every sample of a batch is normalised on its own. All operators take two ``(B, C, H, W)`` tensors of
one floating dtype on one device (any floating dtype, any device) and are differentiable in both.

Example:
    >>> L = torch.rand(2, 512, 7, 7)
    >>> G = torch.randn(2, 512, 7, 7)
    >>> dam(L, G).shape
    torch.Size([2, 512, 7, 7])
    >>> Fusion("gaf")(L, G).shape
    torch.Size([2, 512, 7, 7])
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Callable

import torch
from torch import nn

Tensor = torch.Tensor

__all__ = [
    "FUSION_MODES",
    "Fusion",
    "dam",
    "eam",
    "ega",
    "fuse",
    "gaf",
    "minmax_normalize",
    "no_attention",
]

FUSION_MODES = ("none", "dam", "eam", "gaf", "ega")


def minmax_normalize(x: Tensor, dims: int | Sequence[int], eps: float = 1e-12) -> Tensor:
    """Min-max normalisation to ``[0, 1]`` over ``dims``, independently for every other index.

    ``(x - min) / (max - min)`` with min and max taken over ``dims``. Where ``max - min <= eps`` (a
    constant, or numerically constant, slice) the result is zero. The division uses a safe denominator
    selected with ``torch.where``, so for finite ``x`` neither the forward nor the backward pass produces
    NaN or inf. A slice holding a NaN or an infinity gives NaN throughout (not a map that would hide it:
    an infinity has no place in [0, 1], and the finite values none relative to it).

    Args:
        x: floating-point tensor of any shape ``(*)``.
        dims: the dimension(s) to normalise over, e.g. ``(1, 2, 3)`` for per-sample over ``(C, H, W)``
            of a ``(B, C, H, W)`` tensor. Negative indices are allowed.
        eps: ranges at or below this (finite, >= 0) are treated as constant.

    Returns:
        tensor of the same shape ``(*)``, dtype and device, with values in ``[0, 1]``.

    Example:
        >>> minmax_normalize(torch.tensor([[1.0, 2.0, 3.0], [5.0, 5.0, 5.0]]), dims=1)
        tensor([[0.0000, 0.5000, 1.0000],
                [0.0000, 0.0000, 0.0000]])
    """
    if not isinstance(x, Tensor):
        raise TypeError(f"x must be a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"x must be a floating-point tensor (values in [0, 1] come back in its dtype), got {x.dtype}")
    if not 0 <= float(eps) < float("inf"):
        raise ValueError(f"eps must be a finite number >= 0, got {eps!r}")
    dims = (dims,) if isinstance(dims, int) else tuple(dims)
    if len(dims) == 0:
        raise ValueError("dims must name at least one dimension")
    for d in dims:
        if not -x.dim() <= d < x.dim():
            raise ValueError(f"dims {dims} out of range for a tensor of shape {tuple(x.shape)}")
    lo = torch.amin(x, dim=dims, keepdim=True)
    hi = torch.amax(x, dim=dims, keepdim=True)
    rng = hi - lo
    finite = torch.isfinite(rng)  # a NaN or an infinity in the slice makes its range NaN or inf
    ok = finite & (rng > eps)
    # Safe denominator: 1 where the slice is constant, so x - lo (= 0 there) / 1 stays finite in backward.
    safe = torch.where(ok, rng, torch.ones_like(rng))
    out = torch.where(ok, (x - lo) / safe, torch.zeros_like(x))
    return torch.where(finite, out, torch.full_like(x, float("nan")))


def _check_pair(L: Tensor, G: Tensor) -> None:
    for name, t in (("L", L), ("G", G)):
        if not isinstance(t, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
        if t.dim() != 4:
            raise ValueError(f"{name} must have shape (B, C, H, W), got {tuple(t.shape)}")
        if not t.is_floating_point():
            raise TypeError(f"{name} must be a floating-point tensor, got {t.dtype}")
    if L.shape != G.shape:
        raise ValueError(f"L and G must have the same shape (B, C, H, W), got {tuple(L.shape)} and "
                         f"{tuple(G.shape)}")
    if L.dtype != G.dtype or L.device != G.device:
        raise ValueError(f"L and G must have one dtype and device, got L {L.dtype} on {L.device} and G {G.dtype} "
                         f"on {G.device}")
    if min(L.shape[1:]) < 1:  # N(.) has no min or max over an empty slice
        raise ValueError(f"L and G must have positive C, H and W, got {tuple(L.shape)}")


def _global_attention(G: Tensor) -> Tensor:
    # N over (H, W) of each channel map, summed over channels, then N over (H, W): (B, 1, H, W).
    per_channel = minmax_normalize(G, dims=(2, 3))
    return minmax_normalize(per_channel.sum(dim=1, keepdim=True), dims=(2, 3))


def no_attention(L: Tensor, G: Tensor) -> Tensor:
    """The paper's "none" baseline: returns ``L`` unchanged (``G`` only has its shape checked).

    Args:
        L: layer activations ``(B, C, H, W)``.
        G: attention (guided gradient) ``(B, C, H, W)``, ignored.

    Returns:
        ``L``, shape ``(B, C, H, W)``.
    """
    _check_pair(L, G)
    return L


def dam(L: Tensor, G: Tensor) -> Tensor:
    """Direct attention map: ``L * N(G)``, ``N`` the min-max normalisation over ``(C, H, W)`` per sample.

    Args:
        L: layer activations ``(B, C, H, W)``.
        G: attention (guided gradient) ``(B, C, H, W)``.

    Returns:
        fused activations ``(B, C, H, W)``.

    Example:
        >>> dam(torch.ones(1, 1, 1, 3), torch.tensor([[[[0.0, 1.0, 4.0]]]]))
        tensor([[[[0.0000, 0.2500, 1.0000]]]])
    """
    _check_pair(L, G)
    return L * minmax_normalize(G, dims=(1, 2, 3))


def eam(L: Tensor, G: Tensor) -> Tensor:
    """Exponential attention map: ``L * exp(N(G))``, ``N`` over ``(C, H, W)`` per sample.

    Args:
        L: layer activations ``(B, C, H, W)``.
        G: attention (guided gradient) ``(B, C, H, W)``.

    Returns:
        fused activations ``(B, C, H, W)``.
    """
    _check_pair(L, G)
    return L * torch.exp(minmax_normalize(G, dims=(1, 2, 3)))


def gaf(L: Tensor, G: Tensor) -> Tensor:
    """Global attention fusion: ``L * N(sum_c N(G_c))``.

    The inner ``N`` normalises every channel map ``G_c`` over ``(H, W)``; the sum over channels is
    normalised over ``(H, W)`` again and the resulting ``(B, 1, H, W)`` map is broadcast over channels.

    Args:
        L: layer activations ``(B, C, H, W)``.
        G: attention (guided gradient) ``(B, C, H, W)``.

    Returns:
        fused activations ``(B, C, H, W)``.
    """
    _check_pair(L, G)
    return L * _global_attention(G)


def ega(L: Tensor, G: Tensor) -> Tensor:
    """Exponential global attention: ``L * exp(N(sum_c N(G_c)))`` (see :func:`gaf`).

    Args:
        L: layer activations ``(B, C, H, W)``.
        G: attention (guided gradient) ``(B, C, H, W)``.

    Returns:
        fused activations ``(B, C, H, W)``.
    """
    _check_pair(L, G)
    return L * torch.exp(_global_attention(G))


_OPS: dict[str, Callable[[Tensor, Tensor], Tensor]] = {
    "none": no_attention, "dam": dam, "eam": eam, "gaf": gaf, "ega": ega,
}


def check_fusion_mode(mode: str) -> str:
    if not isinstance(mode, str) or mode.lower() not in _OPS:
        raise ValueError(f"unknown fusion mode {mode!r}; expected one of {FUSION_MODES}")
    return mode.lower()


def fuse(L: Tensor, G: Tensor, mode: str) -> Tensor:
    """Apply the fusion operator named ``mode`` (one of :data:`FUSION_MODES`, case-insensitive).

    Args:
        L: layer activations ``(B, C, H, W)``.
        G: attention (guided gradient) ``(B, C, H, W)``.
        mode: ``"none"``, ``"dam"``, ``"eam"``, ``"gaf"`` or ``"ega"``.

    Returns:
        fused activations ``(B, C, H, W)``.

    Example:
        >>> fuse(torch.rand(2, 8, 7, 7), torch.randn(2, 8, 7, 7), "ega").shape
        torch.Size([2, 8, 7, 7])
    """
    return _OPS[check_fusion_mode(mode)](L, G)


class Fusion(nn.Module):
    """Module wrapper of :func:`fuse`: ``Fusion(mode)(L, G)``; it has no parameters.

    Args:
        mode: ``"none"``, ``"dam"``, ``"eam"``, ``"gaf"`` or ``"ega"`` (case-insensitive).

    Shape:
        - L: ``(B, C, H, W)``
        - G: ``(B, C, H, W)``
        - Output: ``(B, C, H, W)``

    Example:
        >>> fusion = Fusion("dam")
        >>> fusion
        Fusion(mode='dam')
        >>> fusion(torch.rand(1, 4, 7, 7), torch.randn(1, 4, 7, 7)).shape
        torch.Size([1, 4, 7, 7])
    """

    def __init__(self, mode: str = "dam") -> None:
        super().__init__()
        self.mode = check_fusion_mode(mode)

    def forward(self, L: Tensor, G: Tensor) -> Tensor:
        return _OPS[self.mode](L, G)

    def extra_repr(self) -> str:
        return f"mode={self.mode!r}"
