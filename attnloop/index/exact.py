"""Exact scans: the reference search and the kernels every backend re-scores with."""
from __future__ import annotations

import operator

import numpy as np
import torch

Tensor = torch.Tensor

__all__ = ["exact_search", "matvec", "scan_tolerance", "topk_rows"]


def check_count(x, name: str, minimum: int) -> int:
    """An integer setting (int, numpy or 0-d tensor integer) ``>= minimum``; TypeError/ValueError otherwise."""
    try:
        value = operator.index(x)
    except TypeError:
        raise TypeError(f"{name} must be an integer, got {x!r}") from None
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return value


def exact_search(database: Tensor, queries: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """Brute-force reference: the ``k`` rows of ``database`` with the largest dot product per query.

    Args:
        database: ``(N, D)``.
        queries: ``(Q, D)``; the two dtypes are promoted together.
        k: neighbours per query, an integer ``>= 0`` (clipped to ``N``).

    Returns:
        row indices ``(Q, min(k, N))`` (long) and similarities ``(Q, min(k, N))``, most similar first;
        equal similarities in increasing row order (the lower row wins a tie at the ``k``-th place).
    """
    if database.dim() != 2 or queries.dim() != 2 or database.shape[1] != queries.shape[1]:
        raise ValueError(f"need database (N, D) and queries (Q, D), got {tuple(database.shape)} and "
                         f"{tuple(queries.shape)}")
    k = check_count(k, "k", 0)
    dtype = torch.promote_types(database.dtype, queries.dtype)
    sims = queries.to(dtype) @ database.to(dtype).t()
    kk = min(k, database.shape[0])
    vals, rows = torch.topk(sims, kk, dim=1)
    if kk == 0:
        return rows, vals
    # torch.topk orders ties arbitrarily: the lowest rows tied at the k-th value, equal values by row
    kth = vals[:, -1:]
    cut = ((sims >= kth).sum(1) > kk).nonzero().flatten().tolist()
    for i in cut:
        cand = (sims[i] >= kth[i]).nonzero().flatten()  # increasing rows
        order = torch.sort(sims[i, cand], descending=True, stable=True).indices[:kk]
        rows[i] = cand[order]
        vals[i] = sims[i, rows[i]]
    rows, pos = rows.sort(dim=1)
    vals = vals.gather(1, pos)
    order = torch.sort(vals, dim=1, descending=True, stable=True).indices
    return rows.gather(1, order), vals.gather(1, order)


def matvec(a: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``a @ q`` in float32 for ``a (M, D)`` (a view, possibly row-strided) and ``q (D,)``, through torch."""
    return (torch.from_numpy(a) @ torch.from_numpy(q)).numpy()


def scan_tolerance(dim: int, query_norm: float, row_norm: float) -> float:
    """How far below the ``k``-th float32 scan value a row of the true top ``k`` can score.

    A float32 dot product of length ``D`` is off by at most ``~D 2^-24 |x| |q|``: twice that, plus a spacing.
    """
    return (2.0 * dim + 8.0) * 2.0 ** -24 * float(query_norm) * float(row_norm)


def topk_rows(sims: np.ndarray, k: int, tol: float = 0.0) -> np.ndarray:
    """Positions (increasing) of the ``k`` largest values of ``sims (M,)`` and of every value tied with them.

    Every position at least the ``k``-th largest less ``tol`` (all when ``M <= k``), so that the exact
    re-scoring can give ties to the lower row.
    """
    if sims.size <= k:
        return np.arange(sims.size)
    kth = np.partition(sims, sims.size - k)[sims.size - k]
    return np.flatnonzero(sims >= kth - tol)
