"""Timestamp association: evo's nearest-neighbour rule (the default of ``ate``/``rpe``) and TUM's.

:func:`associate_nearest` is evo's ``sync.associate_trajectories``: every stamp of the list with fewer stamps
(the second when both have as many) is matched to the nearest stamp of the other when ``|dt| <= max_difference``
(not one-to-one), in the short list's order, with evo's exact expressions and tie rules.

:func:`associate` is TUM's ``associate.py``: pairs with ``|a - (b + offset)| < max_difference`` are visited by
increasing difference (ties by ``a``, then ``b``) and accepted when neither stamp is taken yet (greedy,
one-to-one), returned sorted by ``a``; candidates come from a binary search, ``O((N + M) log M)``.

Example:
    >>> import torch
    >>> i, j = associate(torch.tensor([0.0, 1.0, 2.0]), torch.tensor([1.005, 0.01, 5.0]))
    >>> i.tolist(), j.tolist()
    ([0, 1], [1, 0])
    >>> i, j = associate_nearest(torch.tensor([0.0, 1.0, 2.0]), torch.tensor([1.005, 0.01, 5.0]))
    >>> i.tolist(), j.tolist()
    ([1, 0], [0, 1])
"""
from __future__ import annotations

from typing import Union

import numpy as np
import torch

__all__ = ["ASSOCIATIONS", "TUM_MAX_DIFFERENCE", "associate", "associate_nearest", "associate_trajectories"]

# TUM's associate.py / evaluate_ate.py default: 20 ms, i.e. less than a frame at 30 Hz.
TUM_MAX_DIFFERENCE = 0.02

# the association rules of ate / rpe: evo's (default) and TUM's
ASSOCIATIONS = ("evo", "tum")

ArrayLike = Union[torch.Tensor, np.ndarray, list]


def _stamps(first: ArrayLike, second: ArrayLike, max_difference: float) -> tuple[np.ndarray, np.ndarray]:
    """``first`` and ``second`` as float64 arrays ``(N,)`` and ``(M,)``, checked with ``max_difference``."""
    out = []
    for name, x in (("first", first), ("second", second)):
        if isinstance(x, torch.Tensor):
            x = x.detach().to("cpu", torch.float64).numpy()
        arr = np.asarray(x, dtype=np.float64)
        if arr.ndim != 1:
            raise ValueError(f"{name} must have shape (N,), got {arr.shape}")
        if not np.isfinite(arr).all():
            raise ValueError(f"{name} contains non-finite timestamps")
        out.append(arr)
    if not max_difference > 0:  # also refuses NaN
        raise ValueError(f"max_difference must be positive, got {max_difference}")
    return out[0], out[1]


def _empty() -> tuple[torch.Tensor, torch.Tensor]:
    return torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long)


def _matching_time_indices(s1: np.ndarray, s2: np.ndarray, max_diff: float,
                           offset_2: float) -> tuple[np.ndarray, np.ndarray]:
    """evo's ``sync.matching_time_indices``, vectorised with the same floating-point expressions (its linear
    search, first minimum, when ``s2`` is not sorted)."""
    s2 = s2 + offset_2
    if not np.all(np.diff(s2) >= 0):
        idx_1, idx_2 = [], []
        chunk = max(1, 4_000_000 // s2.size)
        for start in range(0, s1.size, chunk):
            part = s1[start:start + chunk]
            diffs = np.abs(s2[None, :] - part[:, None])
            best = np.argmin(diffs, axis=1)
            keep = diffs[np.arange(part.size), best] <= max_diff
            idx_1.append(np.flatnonzero(keep) + start)
            idx_2.append(best[keep])
        return np.concatenate(idx_1).astype(np.int64), np.concatenate(idx_2).astype(np.int64)
    inside = ~((s1 < s2[0] - max_diff) | (s1 > s2[-1] + max_diff))
    index = np.minimum(np.searchsorted(s2, s1, side="right"), s2.size - 1)
    diff_ub = s2[index] - s1
    diff_lb = np.where(index > 0, s1 - s2[np.maximum(index - 1, 0)], np.inf)
    upper = (diff_ub <= max_diff) & (diff_ub < diff_lb)
    lower = ~upper & (diff_lb <= max_diff) & (diff_lb <= diff_ub)
    keep = inside & (upper | lower)
    best = np.where(upper, index, index - 1)
    return np.flatnonzero(keep).astype(np.int64), best[keep].astype(np.int64)


def associate_nearest(
    first: ArrayLike,
    second: ArrayLike,
    max_difference: float = TUM_MAX_DIFFERENCE,
    offset: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Match two timestamp lists as evo's ``sync.associate_trajectories(first, second, max_diff, offset_2)``.

    Args:
        first: ``(N,)`` seconds (evo's ``traj_1``, the reference).
        second: ``(M,)`` seconds (``traj_2``, the estimate); ``offset`` is added to them before comparing.
        max_difference: a pair needs ``|dt| <= max_difference`` (closed, as evo).
        offset: time offset added to ``second`` (evo's ``offset_2``).

    Returns:
        ``(K,)`` int64 indices into ``first`` and ``(K,)`` int64 indices into ``second``, in the order of
        the short list's stamps (evo's order); ``K = 0`` (empty tensors) when nothing matches.
    """
    a, b = _stamps(first, second, max_difference)
    if a.size == 0 or b.size == 0:
        return _empty()
    if b.size > a.size:  # evo: second_longer -> the first is the short one
        i, j = _matching_time_indices(a, b, max_difference, offset)
    else:
        j, i = _matching_time_indices(b, a, max_difference, -offset)
    return torch.from_numpy(i), torch.from_numpy(j)


def associate(
    first: ArrayLike,
    second: ArrayLike,
    max_difference: float = TUM_MAX_DIFFERENCE,
    offset: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Match two timestamp lists one-to-one, as TUM's ``associate.py``.

    Args:
        first: ``(N,)`` seconds (any order).
        second: ``(M,)`` seconds (any order); ``offset`` is added to them before comparing.
        max_difference: a pair needs ``|a - (b + offset)| < max_difference`` (strict, as TUM).
        offset: time offset added to ``second``.

    Returns:
        ``(K,)`` int64 indices into ``first`` and ``(K,)`` int64 indices into ``second``, sorted by the
        matched ``first`` stamp; ``K = 0`` (empty tensors) when nothing matches.
    """
    a, b = _stamps(first, second, max_difference)
    empty = _empty()
    if a.size == 0 or b.size == 0:
        return empty

    order_b = np.argsort(b, kind="stable")
    b_sorted = b[order_b] + offset
    # A slightly widened window, then TUM's exact test on the exact same expression.
    margin = max_difference * (1 + 1e-9) + 1e-9
    lo = np.searchsorted(b_sorted, a - margin, side="left")
    hi = np.searchsorted(b_sorted, a + margin, side="right")
    counts = hi - lo
    ia = np.repeat(np.arange(a.size), counts)
    starts = np.repeat(lo - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    ib = order_b[np.arange(ia.size) + starts]
    diff = np.abs(a[ia] - (b[ib] + offset))
    keep = diff < max_difference
    ia, ib, diff = ia[keep], ib[keep], diff[keep]
    if ia.size == 0:
        return empty

    # Python's sort of (diff, a, b) tuples: by difference, then stamp values (then index, for ties).
    order = np.lexsort((ib, ia, b[ib], a[ia], diff))
    used_a = np.zeros(a.size, dtype=bool)
    used_b = np.zeros(b.size, dtype=bool)
    out_a, out_b = [], []
    for k in order.tolist():
        i, j = ia[k], ib[k]
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            out_a.append(i)
            out_b.append(j)
    out_a_np, out_b_np = np.asarray(out_a, dtype=np.int64), np.asarray(out_b, dtype=np.int64)
    final = np.lexsort((b[out_b_np], a[out_a_np]))
    return torch.from_numpy(out_a_np[final]), torch.from_numpy(out_b_np[final])


def association_indices(reference_stamps: ArrayLike, estimate_stamps: ArrayLike, max_difference: float,
                        offset: float, association: str) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`associate_nearest` (``"evo"``) or :func:`associate` (``"tum"``) by name."""
    if association == "evo":
        return associate_nearest(reference_stamps, estimate_stamps, max_difference, offset)
    if association == "tum":
        return associate(reference_stamps, estimate_stamps, max_difference, offset)
    raise ValueError(f"association must be one of {ASSOCIATIONS}, got {association!r}")


def associate_trajectories(reference, estimate, max_difference: float = TUM_MAX_DIFFERENCE, offset: float = 0.0,
                           association: str = "evo"):
    """The associated parts of two trajectories, pair by pair.

    Args:
        reference: a :class:`slam.io.trajectory.Trajectory` (``N`` poses).
        estimate: a :class:`slam.io.trajectory.Trajectory` (``M`` poses); ``offset`` is added to its stamps.
        max_difference: seconds, see :func:`associate_nearest` / :func:`associate`.
        offset: seconds added to the estimate's stamps.
        association: ``"evo"`` (default, :func:`associate_nearest`, evo's ``sync.associate_trajectories``)
            or ``"tum"`` (:func:`associate`, TUM's greedy one-to-one rule).

    Returns:
        ``(reference_part, estimate_part)``, two trajectories of ``K`` poses each, where pose ``k`` of
        one corresponds to pose ``k`` of the other (in evo's order, or sorted by reference time for
        ``"tum"``).
    """
    i, j = association_indices(reference.timestamps, estimate.timestamps, max_difference, offset, association)
    i, j = i.to(reference.timestamps.device), j.to(estimate.timestamps.device)
    return reference.subset(i), estimate.subset(j)
