"""Initial guesses for pose-graph optimisation: a spanning tree of the edges, and the chordal relaxation.

* ``"spanning_tree"``: every pose composed from its component's root along the breadth-first tree of the
  edges (among parallel edges the one with the most information), as g2o's ``computeInitialGuess``.
* ``"chordal"``: GTSAM's ``InitializePose3``: rotations by the chordal relaxation (minimise
  ``sum_e kappa_e |R_i Z_ij - R_j|_F^2`` over 3x3 matrices, ``kappa_e = 3 / (2 tr(Omega_rr^-1))``, then the
  nearest rotations), then translations by least squares weighted by ``R_i Omega_tt R_i^T``.
* ``"auto"``: the graph's own poses when their chi2 per edge is at most :data:`AUTO_CHI2_PER_EDGE`, else
  ``"spanning_tree"``.

Anchors: the graph's ``fixed`` poses and any passed in ``fixed`` keep their values; every connected
component without one keeps the pose of its lowest index. The work runs on the CPU in float64; the result
has the graph's dtype and device.

Example:
    >>> import torch
    >>> from slam.lie import se3_exp, se3_identity
    >>> step = se3_exp(torch.tensor([1.0, 0, 0, 0, 0, 0.3], dtype=torch.float64))
    >>> g = PoseGraph.from_lists([se3_identity(dtype=torch.float64)] * 3, [(0, 1, step), (1, 2, step)])
    >>> P = initial_poses(g, "spanning_tree")
    >>> bool(torch.allclose(P[2], se3_compose(step, step), atol=1e-12))
    True
    >>> bool(torch.allclose(initial_poses(g, "chordal"), P, atol=1e-9))
    True
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Optional

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla
import torch

from slam.graph.costs import graph_chi2
from slam.graph.pose_graph import PoseGraph
from slam.lie import quat_to_rotmat, rotmat_project, rotmat_to_quat, se3_compose, se3_identity, se3_inv

__all__ = ["AUTO_CHI2_PER_EDGE", "INITIALIZATIONS", "SpanningTree", "chordal_poses", "edge_components", "fits_edges",
           "initial_poses", "initialize", "spanning_tree", "spanning_tree_poses"]

Tensor = torch.Tensor

# the initial guesses optimize(graph, initialization=...) accepts ("none": the graph's own poses)
INITIALIZATIONS = ("none", "spanning_tree", "chordal", "auto")

#: ``"auto"`` keeps a graph's poses when their chi2 (``sum r^T Omega r``) is at most this per edge, else composes
#: the spanning tree (the chi2 of one 6-DoF edge at the optimum averages ~6)
AUTO_CHI2_PER_EDGE = 100.0


def fits_edges(chi2: float, num_edges: int) -> bool:
    """Whether poses of chi2 ``chi2`` over ``num_edges`` edges are kept by ``"auto"`` (False for NaN)."""
    return chi2 <= AUTO_CHI2_PER_EDGE * num_edges


@dataclass
class SpanningTree:
    """A spanning forest of a graph's edges (one tree per connected component).

    Attributes:
        parent: ``(N,)`` int64, the parent pose of each pose, ``-1`` for a root.
        edge: ``(N,)`` int64, the edge joining each pose to its parent, ``-1`` for a root.
        roots: ``(C,)`` int64, one root per connected component (isolated poses included).
    """

    parent: np.ndarray
    edge: np.ndarray
    roots: np.ndarray


def _anchors(graph: PoseGraph, fixed: Iterable[int] = ()) -> np.ndarray:
    """``(N,)`` bool: the poses that keep their value (see the module docstring)."""
    n = graph.num_poses
    held = np.zeros(n, dtype=bool)
    held[graph.fixed.cpu().numpy()] = True  # in range: checked by PoseGraph
    extra = np.asarray(list(fixed), dtype=np.int64).reshape(-1)
    if extra.size and (extra.min() < 0 or extra.max() >= n):
        raise ValueError(f"fixed pose index {int(extra[(extra < 0) | (extra >= n)][0])} is out of range [0, {n})")
    held[extra] = True
    ncomp, label = edge_components(graph.ii, graph.jj, graph.num_poses)
    has = np.zeros(ncomp, dtype=bool)
    has[label[held]] = True
    lowest = np.full(ncomp, n, dtype=np.int64)
    np.minimum.at(lowest, label, np.arange(n))
    held[lowest[~has]] = True
    return held


def edge_components(ii: Tensor, jj: Tensor, num_poses: int) -> tuple[int, np.ndarray]:
    """The connected components of the poses joined by the edges ``ii -> jj`` (``(E,)`` each): their number
    and each pose's component ``(N,)`` (numbered in the order of each component's first pose)."""
    i, j = ii.cpu().numpy(), jj.cpu().numpy()
    adj = sp.coo_matrix((np.ones(i.size), (i, j)), shape=(num_poses, num_poses)).tocsr()
    return csgraph.connected_components(adj, directed=False)


def _edge_cost(information: np.ndarray) -> np.ndarray:
    """``(E,)`` trace of each edge's covariance: the tie-break among parallel edges (lower = more certain)."""
    return np.trace(np.linalg.inv(information), axis1=1, axis2=2)


def spanning_tree(graph: PoseGraph, roots: Optional[np.ndarray] = None) -> SpanningTree:
    """The breadth-first spanning forest of ``graph``'s edges.

    Args:
        graph: the :class:`PoseGraph` (its edges are used as undirected).
        roots: ``(N,)`` bool, poses allowed as roots; each component is rooted at its lowest allowed index
            (its lowest index when it has none). Default: the anchors (the graph's fixed poses, else each
            component's lowest index).

    Returns:
        The :class:`SpanningTree`; between two poses joined by several edges, the tree takes the one with
        the smallest covariance trace ``tr(Omega^-1)``.
    """
    n = graph.num_poses
    if roots is None:
        roots = _anchors(graph)
    ncomp, label = edge_components(graph.ii, graph.jj, graph.num_poses)
    cand = np.where(roots, np.arange(n), n)
    root = np.full(ncomp, n, dtype=np.int64)
    np.minimum.at(root, label, cand)
    lowest = np.full(ncomp, n, dtype=np.int64)
    np.minimum.at(lowest, label, np.arange(n))
    root = np.where(root < n, root, lowest)
    parent = np.full(n, -1, dtype=np.int64)
    edge = np.full(n, -1, dtype=np.int64)
    if graph.num_edges == 0:
        return SpanningTree(parent, edge, root)
    ii, jj = graph.ii.cpu().numpy(), graph.jj.cpu().numpy()
    cost = _edge_cost(graph.information.detach().cpu().double().numpy())
    a, b = np.minimum(ii, jj), np.maximum(ii, jj)
    key = a * n + b
    order = np.lexsort((cost, key))  # by vertex pair, then by cost: the first of each pair is its best edge
    first = np.ones(order.size, dtype=bool)
    first[1:] = key[order][1:] != key[order][:-1]
    best = order[first]
    ukey = key[best]
    adj = sp.coo_matrix((np.ones(best.size), (a[best], b[best])), shape=(n, n)).tocsr()
    _, pred, _ = csgraph.dijkstra(adj, directed=False, indices=root, unweighted=True, min_only=True,
                                  return_predecessors=True)
    child = np.nonzero(pred >= 0)[0]
    p = pred[child].astype(np.int64)
    parent[child] = p
    edge[child] = best[np.searchsorted(ukey, np.minimum(p, child) * n + np.maximum(p, child))]
    return SpanningTree(parent, edge, root)


def _compose_tree(tree: SpanningTree, root_poses: Tensor, rel: Tensor) -> Tensor:
    """Poses ``(N, 7)`` from the roots' poses and each pose's pose in its parent's frame ``rel (N, 7)``, by
    pointer jumping: ``A[v] <- A[anc[v]] * A[v]``, ``anc[v] <- anc[anc[v]]`` until every ancestor is a root."""
    n = rel.shape[0]
    ar = np.arange(n)
    anc = np.where(tree.parent < 0, ar, tree.parent)
    A = rel.clone()
    A[torch.from_numpy(tree.parent < 0)] = se3_identity(dtype=rel.dtype)
    while not np.array_equal(anc, anc[anc]):
        A = se3_compose(A[torch.from_numpy(anc)], A)
        anc = anc[anc]
    out = se3_compose(root_poses[torch.from_numpy(anc)], A)
    return torch.cat([out[:, :3], out[:, 3:] / out[:, 3:].norm(dim=-1, keepdim=True)], dim=-1)


def spanning_tree_poses(graph: PoseGraph, fixed: Iterable[int] = ()) -> Tensor:
    """Poses ``(N, 7)`` composed along the breadth-first spanning tree of the edges (see the module docstring).

    Args:
        graph: the :class:`PoseGraph`; only its anchors' poses are used.
        fixed: further pose indices that keep their value (roots of their components).

    Returns:
        ``(N, 7)`` poses in the graph's dtype and on its device; a root keeps its pose. A component with
        several anchors is composed from its lowest one (the others are placed by the tree, so use
        :func:`chordal_poses` to respect them all).
    """
    held = _anchors(graph, fixed)
    tree = spanning_tree(graph, held)
    P = graph.poses.detach().cpu().double()
    Z = graph.measurements.detach().cpu().double()
    n = graph.num_poses
    rel = se3_identity(n, dtype=torch.float64)
    child = np.nonzero(tree.parent >= 0)[0]
    if child.size:
        e = tree.edge[child]
        forward = graph.ii.cpu().numpy()[e] == tree.parent[child]  # edge parent -> child: z; else z^-1
        z = Z[torch.from_numpy(e)]
        rel[torch.from_numpy(child)] = torch.where(torch.from_numpy(forward)[:, None], z, se3_inv(z))
    out = _compose_tree(tree, P, rel)
    out[torch.from_numpy(held)] = P[torch.from_numpy(held)]
    return _finish(graph, out)


def _solve_anchored(A: sp.csr_matrix, rhs: np.ndarray, free_cols: np.ndarray, held_cols: np.ndarray,
                    x_held: np.ndarray) -> np.ndarray:
    """Least squares ``min |A x - rhs|`` over the free columns with ``x[held_cols] = x_held``."""
    A = A.tocsc()
    Af, Ah = A[:, free_cols], A[:, held_cols]
    b = rhs - Ah @ x_held
    H = (Af.T @ Af).tocsc()
    # symmetric mode without pivoting: H is SPD (every component has an anchor)
    lu = spla.splu(H, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return lu.solve(np.asarray(Af.T @ b))


def _edge_matrix(left: np.ndarray, right: np.ndarray, ii: np.ndarray, jj: np.ndarray, n: int) -> sp.csr_matrix:
    """``(3 E, 3 N)``: row block ``e`` holds the 3x3 blocks ``left[e]`` at pose ``ii[e]``, ``right[e]`` at ``jj[e]``."""
    e = ii.shape[0]
    rows = ((3 * np.arange(e))[:, None, None] + np.arange(3)[None, :, None] + np.zeros((1, 1, 3), np.int64)).ravel()
    cols = [((3 * p)[:, None, None] + np.arange(3)[None, None, :] + np.zeros((1, 3, 1), np.int64)).ravel()
            for p in (ii, jj)]
    return sp.coo_matrix((np.concatenate([left.ravel(), right.ravel()]),
                          (np.concatenate([rows, rows]), np.concatenate(cols))), shape=(3 * e, 3 * n)).tocsr()


def _pose_columns(mask: np.ndarray) -> np.ndarray:
    idx = np.nonzero(mask)[0]
    return (3 * idx[:, None] + np.arange(3)).reshape(-1)


def chordal_poses(graph: PoseGraph, fixed: Iterable[int] = ()) -> Tensor:
    """Poses ``(N, 7)`` from the chordal relaxation of the rotations, then least-squares translations.

    Args:
        graph: the :class:`PoseGraph`; only its anchors' poses are used (see the module docstring).
        fixed: further pose indices that keep their value.

    Returns:
        ``(N, 7)`` poses in the graph's dtype and on its device.
    """
    n, e = graph.num_poses, graph.num_edges
    held = _anchors(graph, fixed)
    P = graph.poses.detach().cpu().double()
    if e == 0 or held.all():
        return _finish(graph, P.clone())
    ii, jj = graph.ii.cpu().numpy(), graph.jj.cpu().numpy()
    Z = graph.measurements.detach().cpu().double()
    info = graph.information.detach().cpu().double().numpy()
    Rz = quat_to_rotmat(Z[:, 3:] / Z[:, 3:].norm(dim=-1, keepdim=True)).numpy()  # (E, 3, 3)
    free_cols, held_cols = _pose_columns(~held), _pose_columns(held)

    # rotations: Y_i = R_i^T stacked (3N, 3); residual sqrt(kappa) (Y_j - Z^T Y_i), one 3x3 block per pose
    kappa = 1.5 / np.trace(np.linalg.inv(info[:, 3:, 3:]), axis1=1, axis2=2)
    s = np.sqrt(kappa)[:, None, None]
    eye = np.broadcast_to(np.eye(3), (e, 3, 3))
    A = _edge_matrix(-s * Rz.transpose(0, 2, 1), s * eye, ii, jj, n)
    R_all = quat_to_rotmat(P[:, 3:] / P[:, 3:].norm(dim=-1, keepdim=True)).numpy()
    Y_held = R_all[held].transpose(0, 2, 1).reshape(-1, 3)
    Y_free = _solve_anchored(A, np.zeros((3 * e, 3)), free_cols, held_cols, Y_held)
    R_free = rotmat_project(torch.from_numpy(Y_free.reshape(-1, 3, 3).transpose(0, 2, 1).copy()))
    R_all[~held] = R_free.numpy()

    # translations with the rotations held: residual L^T R_i^T (t_j - t_i) - L^T t_ij, Omega_tt = L L^T
    L = np.linalg.cholesky(info[:, :3, :3])
    B = L.transpose(0, 2, 1) @ R_all[ii].transpose(0, 2, 1)  # (E, 3, 3)
    A = _edge_matrix(-B, B, ii, jj, n)
    rhs = (L.transpose(0, 2, 1) @ Z[:, :3].numpy()[:, :, None])[:, :, 0].reshape(-1)
    t_all = P[:, :3].numpy().copy()
    t_all[~held] = _solve_anchored(A, rhs, free_cols, held_cols, t_all[held].reshape(-1)).reshape(-1, 3)

    out = P.clone()
    out[:, :3] = torch.from_numpy(t_all)
    free_t = torch.from_numpy(~held)
    out[free_t, 3:] = rotmat_to_quat(torch.from_numpy(R_all[~held]))
    return _finish(graph, out)


def _finish(graph: PoseGraph, poses: Tensor) -> Tensor:
    """Planar graphs stay exactly planar (z, qx, qy = 0 up to the round-off of the 3D solve)."""
    if graph.is_planar():
        poses = poses.clone()
        poses[:, 2:5] = 0.0
        poses[:, 3:] = poses[:, 3:] / poses[:, 3:].norm(dim=-1, keepdim=True)
    return poses.to(dtype=graph.poses.dtype, device=graph.poses.device)


def initial_poses(graph: PoseGraph, method: str, fixed: Iterable[int] = ()) -> Tensor:
    """Initial poses ``(N, 7)`` by one of :data:`INITIALIZATIONS` (``"none"`` returns the graph's own)."""
    if not isinstance(graph, PoseGraph):
        raise TypeError(f"graph must be a PoseGraph, got {type(graph).__name__}")
    if method == "none":
        return graph.poses
    if method == "spanning_tree":
        return spanning_tree_poses(graph, fixed)
    if method == "chordal":
        return chordal_poses(graph, fixed)
    if method == "auto":
        return graph.poses if fits_edges(graph_chi2(graph), graph.num_edges) else spanning_tree_poses(graph, fixed)
    raise ValueError(f"initialization must be one of {INITIALIZATIONS}, got {method!r}")


def initialize(graph: PoseGraph, method: str, fixed: Iterable[int] = ()) -> PoseGraph:
    """A copy of ``graph`` (same edges) whose poses are :func:`initial_poses` ``(graph, method, fixed)``."""
    if method == "none":
        return graph
    return graph.with_poses(initial_poses(graph, method, fixed))
