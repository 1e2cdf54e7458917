"""Fusion of a CNN layer ``L`` with its attention map ``G`` (the paper's DAM, EAM, GAF, EGA; docs/method.md).

``N`` is the per-sample min-max normalisation :func:`minmax_normalize`; every operator is differentiable in both.

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


def minmax_normalize(x: Tensor, dims: int | Sequence[int]) -> Tensor:
    """Min-max normalisation ``(x - min) / (max - min)`` over ``dims``, independently for every other index.

    A slice whose range is at most 1e-12 gives zeros (never NaN, also in backward); a slice holding a NaN
    or an infinity gives NaN throughout.

    Args:
        x: floating-point tensor of any shape ``(*)``.
        dims: the dimension(s) to normalise over, e.g. ``(1, 2, 3)`` for per-sample over ``(C, H, W)``.

    Returns:
        tensor of the shape ``(*)``, dtype and device of ``x``, with values in ``[0, 1]``.
    """
    if not x.is_floating_point():
        raise TypeError(f"x must be a floating-point tensor, got {x.dtype}")
    dims = (dims,) if isinstance(dims, int) else tuple(dims)
    if len(dims) == 0:
        raise ValueError("dims must name at least one dimension")
    for d in dims:
        if not -x.dim() <= d < x.dim():
            raise ValueError(f"dims {dims} out of range for a tensor of shape {tuple(x.shape)}")
    lo = torch.amin(x, dim=dims, keepdim=True)
    rng = torch.amax(x, dim=dims, keepdim=True) - lo
    finite = torch.isfinite(rng)
    ok = finite & (rng > 1e-12)
    # a safe denominator where the slice is constant keeps the backward finite
    safe = torch.where(ok, rng, torch.ones_like(rng))
    out = torch.where(ok, (x - lo) / safe, torch.zeros_like(x))
    return torch.where(finite, out, torch.full_like(x, float("nan")))


def check_bchw(x: Tensor, name: str = "x") -> None:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.dim() != 4:
        raise ValueError(f"{name} must have shape (B, C, H, W), got {tuple(x.shape)}")
    if not x.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {x.dtype}")


def _check_pair(L: Tensor, G: Tensor) -> None:
    check_bchw(L, "L")
    check_bchw(G, "G")
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
    """The ``none`` baseline: ``L`` unchanged, ``(B, C, H, W)`` (``G``, same shape, only checked)."""
    _check_pair(L, G)
    return L


def dam(L: Tensor, G: Tensor) -> Tensor:
    """Direct attention map ``L * N(G)``: activations ``L`` and attention ``G`` ``(B, C, H, W)`` -> ``(B, C, H, W)``."""
    _check_pair(L, G)
    return L * minmax_normalize(G, dims=(1, 2, 3))


def eam(L: Tensor, G: Tensor) -> Tensor:
    """Exponential attention map ``L * exp(N(G))``: ``L``, ``G`` ``(B, C, H, W)`` -> ``(B, C, H, W)``."""
    _check_pair(L, G)
    return L * torch.exp(minmax_normalize(G, dims=(1, 2, 3)))


def gaf(L: Tensor, G: Tensor) -> Tensor:
    """Global attention fusion ``L * N(sum_c N(G_c))``: ``L``, ``G`` ``(B, C, H, W)`` -> ``(B, C, H, W)``.

    The inner ``N`` over ``(H, W)`` of each channel map, the outer over ``(H, W)`` of their sum.
    """
    _check_pair(L, G)
    return L * _global_attention(G)


def ega(L: Tensor, G: Tensor) -> Tensor:
    """Exponential global attention ``L * exp(N(sum_c N(G_c)))``: ``(B, C, H, W)`` each -> ``(B, C, H, W)``."""
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
    """The fusion named ``mode`` (case-insensitive): ``L``, ``G`` ``(B, C, H, W)`` -> ``(B, C, H, W)``."""
    return _OPS[check_fusion_mode(mode)](L, G)


class Fusion(nn.Module):
    """Module wrapper of :func:`fuse` (no parameters).

    Args:
        mode: ``"none"``, ``"dam"``, ``"eam"``, ``"gaf"`` or ``"ega"`` (case-insensitive).

    Shape:
        - L, G: ``(B, C, H, W)``
        - Output: ``(B, C, H, W)``
    """

    def __init__(self, mode: str = "dam") -> None:
        super().__init__()
        self.mode = check_fusion_mode(mode)

    def forward(self, L: Tensor, G: Tensor) -> Tensor:
        return _OPS[self.mode](L, G)

    def extra_repr(self) -> str:
        return f"mode={self.mode!r}"
