"""Regional GeM pooling of fused attention maps: the translation-tolerant code of the default descriptor.

Per tap group, GeM over the whole map and a 2 x 2 grid (by default), each region L2-normalised, concatenated
``[group][region][channel]``; why: docs/method.md.

Example:
    >>> x = torch.rand(2, 512, 7, 9)
    >>> regional_code(x, groups=(192, 320)).shape
    torch.Size([2, 2560])
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F

from .fusion import check_bchw, check_fusion_mode, fuse

Tensor = torch.Tensor

__all__ = ["POOLINGS", "fuse_groups", "gem_regions", "regional_code", "regional_code_dim", "unit_scale"]

#: ``flat``: the paper's one-level RNN over the whole fused map; ``regional``: regional GeM first (ours).
POOLINGS = ("flat", "regional")

# GeM's floor, relative to each sample's max |x|: an absolute floor would swamp a map of small magnitude.
_REL_FLOOR = 1e-6
# A region whose unit-scaled GeM is at most this is empty (all values at the floor, with rounding margin).
_EMPTY_REGION = 2 * _REL_FLOOR


def _check_levels(levels: Sequence[int]) -> tuple[int, ...]:
    lv = tuple(int(v) for v in levels)
    if not lv or any(v < 1 for v in lv) or any(int(v) != v for v in levels):
        raise ValueError(f"levels must be positive grid sizes such as (1, 2), got {levels!r}")
    return lv


def _check_groups(channels: int, groups: Sequence[int] | None) -> tuple[int, ...]:
    if groups is None:
        return (channels,)
    g = tuple(int(v) for v in groups)
    if any(v < 1 for v in g) or sum(g) != channels:
        raise ValueError(f"groups {tuple(groups)} must be positive channel counts summing to the {channels} "
                         "channels of the map")
    return g


def _check_map(x: Tensor, name: str = "x") -> None:
    check_bchw(x, name)  # a floating (B, C, H, W) tensor, as the RNN pooling takes
    if x.shape[0] > 0 and min(x.shape[1:]) < 1:
        raise ValueError(f"{name} must have positive C, H and W, got {tuple(x.shape)}")


def _check_p(p: float) -> None:
    if not (p > 0 and math.isfinite(p)):
        raise ValueError(f"p must be positive and finite (the GeM exponent), got {p}")


def unit_scale(grad: Tensor) -> Tensor:
    """G / max|G| per sample, :math:`(B, *)` -> same shape (an all-zero G stays zero)."""
    if not isinstance(grad, Tensor):
        raise TypeError(f"grad must be a torch.Tensor, got {type(grad).__name__}")
    if grad.ndim < 1 or not grad.is_floating_point():
        raise ValueError(f"grad must be a floating-point tensor (B, *), got {grad.dtype} {tuple(grad.shape)}")
    # (B,): each sample is one value (amax over no dimension would reduce over the batch)
    peak = grad.detach().abs() if grad.ndim == 1 else grad.detach().abs().amax(dim=tuple(range(1, grad.ndim)),
                                                                             keepdim=True)
    return grad / peak.clamp_min(torch.finfo(grad.dtype).tiny)


def fuse_groups(tap: Tensor, grad: Tensor, mode: str, groups: Sequence[int] | None = None,
                attended: Sequence[bool] | None = None) -> Tensor:
    """Fuse (L, G) with ``mode`` separately on each channel group, G scaled to max |G| = 1 per group.

    Args:
        tap: L, :math:`(B, C, H, W)`.
        grad: G, :math:`(B, C, H, W)`.
        mode: a fusion mode (:data:`attnloop.fusion.FUSION_MODES`).
        groups: channel counts of the groups (e.g. ``(192, 320)``), summing to C; None: one group.
        attended: per group, whether it is fused (the backbone's ``attended_groups``: G is computed
            there); a group not attended passes L unchanged, as ``none`` does. None: every group.

    Returns:
        the fused map :math:`(B, C, H, W)`.
    """
    _check_map(tap, "tap")
    _check_map(grad, "grad")
    if tap.shape != grad.shape:
        raise ValueError(f"tap and grad must have one shape (B, C, H, W), got {tuple(tap.shape)} and "
                         f"{tuple(grad.shape)}")
    g = _check_groups(tap.shape[1], groups)
    att = (True,) * len(g) if attended is None else tuple(bool(a) for a in attended)
    if len(att) != len(g):
        raise ValueError(f"attended has {len(att)} flags for {len(g)} groups {g}")
    if check_fusion_mode(mode) == "none":  # checked also where no group is fused
        return tap
    if len(g) == 1:
        return fuse(tap, unit_scale(grad), mode) if att[0] else tap
    return torch.cat([fuse(lt, unit_scale(gt), mode) if a else lt
                      for lt, gt, a in zip(tap.split(g, 1), grad.split(g, 1), att)], dim=1)


def _unit_gem_regions(x: Tensor, p: float, levels: tuple[int, ...],
                      groups: tuple[int, ...] | None = None) -> tuple[Tensor, Tensor]:
    # GeM of x / s, s = max |x| per sample and channel group, keeping x^p in float range: (B, R, C) and s
    # per channel (B, 1, C).
    g = groups or (x.shape[1],)
    peak = x.abs().amax(dim=(2, 3))  # (B, C)
    scales = []
    for pg, c in zip(peak.split(g, dim=1), g):
        top = pg.amax(dim=1, keepdim=True)
        # an all-zero group stays at the floor, no NaN
        scales.append(torch.where(top > 0, top, torch.ones_like(top)).expand(-1, c))
    safe = torch.cat(scales, dim=1)
    xp = (x / safe[:, :, None, None]).clamp_min(_REL_FLOOR).pow(p)
    cells = [F.adaptive_avg_pool2d(xp, v).flatten(2) for v in levels]  # (B, C, l*l) each
    return torch.cat(cells, dim=2).pow(1.0 / p).transpose(1, 2), safe[:, None, :]


def gem_regions(x: Tensor, p: float = 2.0, levels: Sequence[int] = (1, 2)) -> Tensor:
    """GeM pooling over the whole map and the cells of square grids.

    ``(mean_{cell} max(x, eps)^p)^(1/p)`` per channel, ``eps = 1e-6 max|x|`` per sample (so
    ``gem_regions(k x) = k gem_regions(x)``, k > 0); grids as :func:`torch.nn.functional.adaptive_avg_pool2d`.

    Args:
        x: :math:`(B, C, H, W)`.
        p: the GeM exponent (finite, > 0).
        levels: grid sizes; ``(1, 2)`` gives the whole map and a 2 x 2 grid, 5 regions.

    Returns:
        :math:`(B, R, C)` with ``R = sum_l l^2``, regions in the order of ``levels``, cells row-major.
    """
    _check_map(x)
    _check_p(p)
    lv = _check_levels(levels)
    if x.shape[0] == 0:
        return x.new_zeros((0, sum(v * v for v in lv), x.shape[1]))
    unit, scale = _unit_gem_regions(x, p, lv)
    zero = x.abs().amax(dim=(1, 2, 3)) == 0
    return torch.where(zero.view(-1, 1, 1), torch.zeros_like(unit), unit * scale)


def regional_code_dim(groups: Sequence[int], levels: Sequence[int] = (1, 2)) -> int:
    """Length of :func:`regional_code`'s output: ``sum_l l^2 * sum_g C_g``."""
    g = tuple(groups)
    if not g or any(isinstance(c, bool) or int(c) != c or c < 1 for c in g):
        raise ValueError(f"groups must be positive channel counts such as (192, 320), got {groups!r}")
    return sum(v * v for v in _check_levels(levels)) * sum(int(c) for c in g)


def regional_code(x: Tensor, groups: Sequence[int] | None = None, p: float = 2.0,
                  levels: Sequence[int] = (1, 2)) -> Tensor:
    """Regional GeM code of a fused map: per group and region a unit vector, all concatenated.

    Args:
        x: the fused map :math:`(B, C, H, W)`.
        groups: channel counts of the tap groups (summing to C); None: one group.
        p: the GeM exponent.
        levels: grid sizes (see :func:`gem_regions`).

    Returns:
        :math:`(B, D)`, ``D = regional_code_dim(groups, levels)``; a region with no value above the floor
        gives zeros (no evidence), not the uniform vector its floor would normalise to.
    """
    _check_map(x)
    g = _check_groups(x.shape[1], groups)
    _check_p(p)
    lv = _check_levels(levels)
    if x.shape[0] == 0:
        return x.new_zeros((0, regional_code_dim(g, lv)))
    unit = _unit_gem_regions(x, p, lv, g)[0]  # (B, R, C)
    parts = [F.normalize(ug * (ug.amax(dim=2, keepdim=True) > _EMPTY_REGION), dim=2).flatten(1)
             for ug in unit.split(g, dim=2)]
    return torch.cat(parts, dim=1)
