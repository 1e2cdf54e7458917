"""Timestamp association exactly as TUM's ``associate.py``.

TUM's algorithm: every pair ``(a, b)`` with ``|a - (b + offset)| < max_difference`` is a candidate;
candidates are visited by increasing difference (ties by ``a``, then ``b``) and a pair is accepted
when neither of its stamps is taken yet (greedy, one-to-one); the matches are returned sorted by
``a``. Here the candidates come from a binary search instead of TUM's all-pairs loop, so it runs in
``O((N + M) log M)`` for sensor streams.

evo's ``sync.associate_trajectories`` differs slightly (nearest neighbour per pose of the shorter
trajectory, not one-to-one, ``<=`` instead of ``<``); on real sensor streams both give the same pairs.

Example:
    >>> import torch
    >>> i, j = associate(torch.tensor([0.0, 1.0, 2.0]), torch.tensor([1.005, 0.01, 5.0]))
    >>> i.tolist(), j.tolist()
    ([0, 1], [1, 0])
"""
from __future__ import annotations

from typing import Union

import numpy as np
import torch

__all__ = ["TUM_MAX_DIFFERENCE", "associate", "associate_trajectories"]

# TUM's associate.py / evaluate_ate.py default: 20 ms, i.e. less than a frame at 30 Hz.
TUM_MAX_DIFFERENCE = 0.02

ArrayLike = Union[torch.Tensor, np.ndarray, list]


def _stamps(x: ArrayLike, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().to("cpu", torch.float64).numpy()
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != 1:
        raise ValueError(f"{name} must have shape (N,), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains non-finite timestamps")
    return arr


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
    a = _stamps(first, "first")
    b = _stamps(second, "second")
    if max_difference <= 0:
        raise ValueError(f"max_difference must be positive, got {max_difference}")
    empty = (torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long))
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


def associate_trajectories(reference, estimate, max_difference: float = TUM_MAX_DIFFERENCE, offset: float = 0.0):
    """The associated parts of two trajectories, pair by pair.

    Args:
        reference: a :class:`slam.io.trajectory.Trajectory` (``N`` poses).
        estimate: a :class:`slam.io.trajectory.Trajectory` (``M`` poses); ``offset`` is added to its stamps.
        max_difference: seconds, see :func:`associate`.
        offset: seconds added to the estimate's stamps.

    Returns:
        ``(reference_part, estimate_part)``, two trajectories of ``K`` poses each, where pose ``k`` of
        one corresponds to pose ``k`` of the other (sorted by reference time).
    """
    i, j = associate(reference.timestamps, estimate.timestamps, max_difference, offset)
    i, j = i.to(reference.timestamps.device), j.to(estimate.timestamps.device)
    return reference.subset(i), estimate.subset(j)
