"""Sparse normal equations of a pose graph and pluggable solvers for them.

``H dx = -g`` has one ``k x k`` block (``k = 6``, or ``3`` when planar) per pair of connected free poses; the
pattern is built once (:func:`build_pattern`), ``H`` stored block-major as ``values (nb * k * k,)``.
"""
from __future__ import annotations

import abc
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Union

import numpy as np
import torch

__all__ = [
    "DENSE_MAX",
    "BlockPattern",
    "DenseCholeskySolver",
    "LinearSolver",
    "LinearSolverError",
    "SparseCholeskySolver",
    "assemble_blocks",
    "build_pattern",
    "make_solver",
    "to_dense",
]

Tensor = torch.Tensor


class LinearSolverError(RuntimeError):
    """The linear system could not be solved (singular / indefinite / did not converge)."""


@dataclass
class BlockPattern:
    """Block sparsity pattern of the reduced normal equations (free poses only), symmetric.

    Attributes:
        num_vars: number of free poses ``n``.
        k: unknowns per pose (6, or 3 for planar problems).
        var_index: ``(N,)`` long, the variable of each pose, ``-1`` for a fixed pose.
        block_rows: ``(nb,)`` long block row of each stored block (sorted by row, then column).
        block_cols: ``(nb,)`` long block column of each stored block.
        diag_blocks: ``(n,)`` long, the block id of each diagonal block.
        diag_pos: ``(n k,)`` long, position of each diagonal entry of ``H`` in the value array.
        edge_blocks: ``(E, 4)`` long, block ids of an edge's ``(i, i), (i, j), (j, i), (j, j)`` blocks;
            ``nb`` (a dump block) where a fixed pose is involved.
        edge_vars: ``(E, 2)`` long, variables of ``i`` and ``j``; ``n`` (a dump row) for a fixed pose.
    """

    num_vars: int
    k: int
    var_index: Tensor
    block_rows: Tensor
    block_cols: Tensor
    diag_blocks: Tensor
    diag_pos: Tensor
    edge_blocks: Tensor
    edge_vars: Tensor
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def size(self) -> int:
        return self.num_vars * self.k

    @property
    def num_blocks(self) -> int:
        return int(self.block_rows.shape[0])

    @property
    def nnz(self) -> int:
        return self.num_blocks * self.k * self.k


def build_pattern(ii: Tensor, jj: Tensor, free: Tensor, k: int = 6) -> BlockPattern:
    """Build the symmetric block pattern of ``H`` for edges ``(ii, jj)``.

    Args:
        ii, jj: ``(E,)`` long, the first and second pose of each edge.
        free: ``(N,)`` bool, the poses that are optimised (the others are held fixed).
        k: unknowns per pose.

    Returns:
        The :class:`BlockPattern`.
    """
    if ii.dim() != 1 or ii.shape != jj.shape:
        raise ValueError(f"ii and jj must have shape (E,), got {tuple(ii.shape)} and {tuple(jj.shape)}")
    if free.dim() != 1 or free.dtype != torch.bool:
        raise ValueError(f"free must be a bool tensor of shape (N,), got {free.dtype} {tuple(free.shape)}")
    dev = ii.device  # index bookkeeping in numpy, the results moved to the indices' device
    ii_, jj_, free_ = ii.cpu().numpy(), jj.cpu().numpy(), free.cpu().numpy()
    n = int(free_.sum())
    nn = max(n, 1)
    var = np.where(free_, np.cumsum(free_) - 1, -1)
    vi, vj = var[ii_], var[jj_]
    both = (vi >= 0) & (vj >= 0)
    ar = np.arange(n)
    keys = np.unique(np.concatenate([ar * nn + ar, vi[both] * nn + vj[both], vj[both] * nn + vi[both]]))
    nb = keys.shape[0]
    # block id of (r, c) by binary search in the sorted keys; the dump block nb where a pose is fixed
    r = np.stack([vi, vi, vj, vj], -1).reshape(-1, 4)
    c = np.stack([vi, vj, vi, vj], -1).reshape(-1, 4)
    ok = (r >= 0) & (c >= 0)
    edge_blocks = np.where(ok, np.searchsorted(keys, np.where(ok, r * nn + c, 0)), nb)
    diag_blocks = np.searchsorted(keys, ar * nn + ar)
    diag_pos = ((diag_blocks * (k * k))[:, None] + np.arange(k) * (k + 1)).reshape(-1)
    edge_vars = np.stack([vi, vj], -1).reshape(-1, 2)
    edge_vars = np.where(edge_vars >= 0, edge_vars, n)

    def t(a):
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.int64)).to(dev)

    return BlockPattern(n, k, t(var), t(keys // nn), t(keys % nn), t(diag_blocks), t(diag_pos), t(edge_blocks),
                        t(edge_vars))


def assemble_blocks(pattern: BlockPattern, blocks: Tensor, g_edges: Tensor, out=None):
    """Add the per-edge blocks of ``J^T W Omega J`` (``(E, 2, 2, k, k)`` or ``(E, 4, k, k)``: ii, ij, ji, jj) and
    of ``J^T W Omega r`` (``g_edges (E, 2, k)``) into the sparse system: ``values (nb k k,)`` of ``H`` (block-major)
    and the gradient ``g (n k,)``. ``out``: optional ``(H (nb + 1, k, k), g (n + 1, k))`` buffers to sum into
    (zeroed first; the returned values are views of them)."""
    k, E = pattern.k, blocks.shape[0]
    if out is None:
        H = torch.zeros(pattern.num_blocks + 1, k, k, dtype=blocks.dtype, device=blocks.device)
        g = torch.zeros(pattern.num_vars + 1, k, dtype=g_edges.dtype, device=g_edges.device)
    else:
        H, g = out[0].zero_(), out[1].zero_()
    H.view(-1, k * k).index_add_(0, pattern.edge_blocks.view(-1), blocks.reshape(E * 4, k * k))
    g.index_add_(0, pattern.edge_vars.view(-1), g_edges.reshape(E * 2, k))
    return H[:-1].view(-1), g[:-1].view(-1)


def to_dense(pattern: BlockPattern, values: Tensor) -> Tensor:
    """The dense ``(n k, n k)`` matrix of block-major ``values``."""
    n, k = pattern.num_vars, pattern.k
    A = torch.zeros(n, n, k, k, dtype=values.dtype, device=values.device)
    A[pattern.block_rows.to(values.device), pattern.block_cols.to(values.device)] = values.view(-1, k, k)
    return A.permute(0, 2, 1, 3).reshape(n * k, n * k)


#: Symbolic analyses kept between calls (each holds its factor's workspace, the size of the factor).
SYMBOLIC_CACHE_SIZE = 2
_SYMBOLIC: OrderedDict = OrderedDict()  # pattern key -> SymbolicCholesky, least recently used first
_SYMBOLIC_LOCK = threading.Lock()


class LinearSolver(abc.ABC):
    """A solver of the SPD system ``H x = b`` held as a block pattern (subclass it to plug in another
    factorisation, e.g. CHOLMOD through scikit-sparse, and pass the object as ``optimize(..., solver=obj)``)."""

    @abc.abstractmethod
    def solve(self, pattern: BlockPattern, values: Tensor, b: Tensor) -> Tensor:
        """``x (n k,)`` for the block values ``values (nnz,)`` of ``H`` on ``pattern`` and ``b (n k,)``."""


class SparseCholeskySolver(LinearSolver):
    """Supernodal sparse Cholesky (:class:`slam.graph.cholesky.SymbolicCholesky`), float64."""

    def symbolic(self, pattern: BlockPattern):
        """The analysis of ``pattern``, kept on it and for the last :data:`SYMBOLIC_CACHE_SIZE` patterns."""
        from slam.graph.cholesky import SymbolicCholesky

        sym = pattern._cache.get("symbolic")
        if sym is None:
            key = (pattern.k, pattern.num_vars, pattern.block_rows.cpu().numpy().tobytes(),
                   pattern.block_cols.cpu().numpy().tobytes())
            with _SYMBOLIC_LOCK:
                sym = _SYMBOLIC.pop(key, None)
            sym = sym or SymbolicCholesky(pattern)
            with _SYMBOLIC_LOCK:
                _SYMBOLIC[key] = sym  # most recently used last
                while len(_SYMBOLIC) > SYMBOLIC_CACHE_SIZE:
                    _SYMBOLIC.popitem(last=False)
            pattern._cache["symbolic"] = sym
        return sym

    def solve(self, pattern: BlockPattern, values: Tensor, b: Tensor) -> Tensor:
        from slam.graph.cholesky import NotPositiveDefiniteError

        sym = self.symbolic(pattern)
        try:
            fac = sym.factor(values.detach().to(torch.float64))
        except NotPositiveDefiniteError as exc:
            raise LinearSolverError(str(exc)) from None
        x = fac.solve(b.detach().to(torch.float64))
        if not bool(torch.isfinite(x).all()):
            raise LinearSolverError("sparse Cholesky produced non-finite values (singular system)")
        return x.to(b.dtype)


class DenseCholeskySolver(LinearSolver):
    """Dense ``torch.linalg.cholesky_ex`` + triangular solves (pure torch, follows the device)."""

    def solve(self, pattern: BlockPattern, values: Tensor, b: Tensor) -> Tensor:
        A = to_dense(pattern, values)
        L, info = torch.linalg.cholesky_ex(A)
        if int(info) != 0:
            raise LinearSolverError("dense Cholesky failed: the matrix is not positive definite "
                                    f"(leading minor {int(info)})")
        return torch.cholesky_solve(b[:, None], L)[:, 0]


#: ``"auto"`` takes the dense Cholesky up to this many unknowns (40 poses), the sparse one above
DENSE_MAX = 240


def make_solver(solver: Union[None, str, LinearSolver], size: int = 0) -> LinearSolver:
    """A :class:`LinearSolver` object as given, or one by name (``"auto"``, ``"sparse"``, ``"dense"``);
    ``"auto"`` (or None) is the dense Cholesky up to :data:`DENSE_MAX` unknowns, else the sparse one."""
    if isinstance(solver, LinearSolver):
        return solver
    name = "auto" if solver is None else str(solver).lower()
    if name == "auto":
        name = "dense" if size <= DENSE_MAX else "sparse"
    if name == "sparse":
        return SparseCholeskySolver()
    if name == "dense":
        return DenseCholeskySolver()
    raise ValueError(f"unknown linear solver {solver!r}; expected 'auto', 'sparse', 'dense' or a LinearSolver")
