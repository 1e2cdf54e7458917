"""Exact scans: the reference search and the kernels every backend re-scores with."""
from __future__ import annotations

import numpy as np
import torch

Tensor = torch.Tensor

__all__ = ["exact_search", "matvec", "topk_rows"]


def exact_search(database: Tensor, queries: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """Brute-force reference: the ``k`` rows of ``database`` with the largest dot product per query.

    Args:
        database: ``(N, D)``.
        queries: ``(Q, D)``.
        k: neighbours per query (clipped to ``N``).

    Returns:
        row indices ``(Q, min(k, N))`` (long) and similarities ``(Q, min(k, N))``, most similar first.

    Example:
        >>> rows, sims = exact_search(torch.eye(3), torch.tensor([[0.1, 0.9, 0.0]]), k=2)
        >>> rows.tolist()
        [[1, 0]]
    """
    if database.dim() != 2 or queries.dim() != 2 or database.shape[1] != queries.shape[1]:
        raise ValueError(f"need database (N, D) and queries (Q, D), got {tuple(database.shape)} and "
                         f"{tuple(queries.shape)}")
    kk = min(int(k), database.shape[0])
    sims = queries @ database.t()
    vals, rows = torch.topk(sims, kk, dim=1)
    return rows, vals


def matvec(a: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``a @ q`` in float32 for ``a (M, D)`` (a view, possibly row-strided) and ``q (D,)``.

    Through torch: numpy's gemv was up to 10x slower and erratic on a busy 2-core machine.
    """
    if a.shape[0] == 0:
        return np.zeros(0, dtype=np.float32)
    return (torch.from_numpy(a) @ torch.from_numpy(q)).numpy()


def topk_rows(sims: np.ndarray, k: int) -> np.ndarray:
    """Positions of the ``k`` largest values of ``sims (M,)`` (unordered; all of them when ``M <= k``)."""
    if sims.size <= k:
        return np.arange(sims.size)
    return np.argpartition(-sims, k - 1)[:k]
