"""The keyframe pose graph the SLAM system builds: keyframe poses and typed edges (odometry / loop).

Two poses per keyframe: the *odometry* pose (the chain of odometry edges from keyframe 0) and the current
*estimate* (corrected by the loops optimised so far). Distances along the graph bound the drift between two
keyframes (:meth:`KeyframeGraph.path_lengths`); a weak edge (forced after a tracking loss) bounds nothing.

Example:
    >>> import torch
    >>> from slam.lie import se3_compose, se3_exp, se3_identity
    >>> g = KeyframeGraph()
    >>> step = se3_exp(torch.tensor([0.5, 0, 0, 0, 0, 0], dtype=torch.float64))
    >>> info = torch.eye(6, dtype=torch.float64)
    >>> g.add_keyframe(se3_identity(dtype=torch.float64))
    0
    >>> for k in range(1, 4):
    ...     _ = g.add_odometry(k - 1, step, info, estimate=se3_compose(g.estimate(k - 1), step))
    >>> g.add_loop(0, 3, se3_exp(torch.tensor([1.45, 0, 0, 0, 0, 0], dtype=torch.float64)), info)
    3
    >>> g.num_keyframes, g.num_edges, g.edge_kind_codes(torch.arange(4)).tolist()
    (4, 4, [0, 0, 0, 1])
    >>> [round(float(d), 2) for d in g.path_lengths(0, through_loops=False)]
    [0.0, 0.5, 1.0, 1.5]
    >>> [round(float(d), 2) for d in g.path_lengths(0, through_loops=True)]
    [0.0, 0.5, 1.0, 1.45]
"""
from __future__ import annotations

import heapq
import itertools
import math
from dataclasses import dataclass
from enum import IntEnum
from typing import Dict, List, Optional

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from slam.graph import PoseGraph
from slam.lie import se3_compose

Tensor = torch.Tensor

__all__ = ["EdgeKind", "GraphEdge", "GrowingArray", "KeyframeGraph"]


class GrowingArray:
    """A numpy array that grows by rows in amortised O(1) (capacity doubling): :attr:`view` is its rows so far.

    Example:
        >>> a = GrowingArray(np.float64)
        >>> a.append(1.5); a.append(2.0)
        >>> a.view.tolist(), len(a)
        ([1.5, 2.0], 2)
    """

    def __init__(self, dtype, row_shape: tuple = ()):
        self._buf = np.zeros((8, *row_shape), dtype=dtype)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def append(self, row) -> None:
        if self._n == self._buf.shape[0]:
            grown = np.zeros((2 * self._n, *self._buf.shape[1:]), dtype=self._buf.dtype)
            grown[: self._n] = self._buf
            self._buf = grown
        self._buf[self._n] = row
        self._n += 1

    @property
    def view(self) -> np.ndarray:
        """The rows so far (a view: it changes with the next append that does not reallocate)."""
        return self._buf[: self._n]


def _f64(t: Tensor) -> Tensor:
    """``t`` as a float64 CPU tensor without grad: itself when it is one already (no new tensor)."""
    return (t.detach() if t.requires_grad else t).to(torch.float64).cpu()


class EdgeKind(IntEnum):
    """What an edge of the keyframe graph measures (the integer is its code: :meth:`KeyframeGraph.edge_kind_codes`)."""

    ODOMETRY = 0  # consecutive keyframes, from the front end's registration
    LOOP = 1  # a verified revisit between keyframes far apart in time


@dataclass
class GraphEdge:
    """One edge ``i -> j`` of the keyframe graph.

    Attributes:
        i, j: keyframe ids.
        T_ij: ``(7,)`` float64 measured pose of keyframe j in keyframe i.
        information: ``(6, 6)`` float64 information of ``T_ij`` as the registration computed it (right
            perturbation, ``[rho, phi]``), before the back end's per-kind scaling.
        kind: :class:`EdgeKind`.
        weak: an odometry edge forced after a tracking loss (constant-velocity guess).
        active: False for a loop edge taken out of the graph (outside the consistent group of loops);
            inactive edges stay in the list (and in :meth:`KeyframeGraph.pose_graph` only when asked for)
            so that edge indices remain stable.
        weight: the back end's last robust-kernel weight of the edge (1 before any optimisation).
    """

    i: int
    j: int
    T_ij: Tensor
    information: Tensor
    kind: EdgeKind
    weak: bool = False
    active: bool = True
    weight: float = 1.0

    @property
    def length(self) -> float:
        """Translation of the measurement (metres)."""
        return float(self.T_ij[:3].norm())


class KeyframeGraph:
    """Keyframe poses (odometry and estimate) and typed edges; builds the :class:`~slam.graph.PoseGraph`.

    Keyframe ids are ``0 .. num_keyframes - 1`` in creation order; a keyframe other than the first enters with its
    odometry edge (:meth:`add_odometry`), which sets its odometry pose by composition. An edge keeps the float64
    tensors it is given (a loop's edge and its :class:`slam.loop.LoopClosure` hold one pair): they must not be
    changed in place afterwards.
    """

    def __init__(self) -> None:
        # per keyframe its poses, per edge its measurement and information: rows, read and replaced as blocks
        self._odometry = GrowingArray(np.float64, (7,))
        self._estimate = GrowingArray(np.float64, (7,))
        self._edge_T = GrowingArray(np.float64, (7,))
        self._edge_info = GrowingArray(np.float64, (6, 6))
        self.edges: List[GraphEdge] = []
        # metres from keyframe 0 along the odometry edges while they form a chain: distances are differences
        self._travelled = GrowingArray(np.float64)
        self._weak_before = GrowingArray(np.int64)  # weak edges on the chain from keyframe 0
        self._chain = True
        self._joined: list[set[int]] = []  # per keyframe, the keyframes an edge joins it to
        self._incident: list[list[int]] = []  # per keyframe, the indices of its edges
        self._edge_length = GrowingArray(np.float64)  # per edge, |t_ij|
        self._edge_ij = GrowingArray(np.int64, (2,))  # per edge, its ends
        self._edge_kind = GrowingArray(np.int64)  # per edge, its EdgeKind code
        self._odometry_of: list[list[int]] = []  # per keyframe, its odometry edges
        self._loops_of: list[list[int]] = []  # per keyframe, its loop edges, oldest first

    @property
    def num_keyframes(self) -> int:
        return len(self._odometry)

    @property
    def num_edges(self) -> int:
        return len(self.edges)

    def add_keyframe(self, pose: Tensor) -> int:
        """Add a keyframe with no edge (the first one; or a map's origin). Returns its id."""
        p = pose.detach().to(torch.float64).cpu().clone()
        self._chain = self._chain and not len(self._odometry)
        return self._append_keyframe(p.numpy(), p.numpy(), 0.0, 0, set())

    def _append_keyframe(self, odometry: np.ndarray, estimate: np.ndarray, travelled: float, weak_before: int,
                         joined: set[int]) -> int:
        self._odometry.append(odometry)
        self._estimate.append(estimate)
        self._travelled.append(travelled)
        self._weak_before.append(weak_before)
        self._joined.append(joined)
        for rows in (self._incident, self._odometry_of, self._loops_of):
            rows.append([])
        return len(self._odometry) - 1

    def add_odometry(self, i: int, T_ij: Tensor, information: Tensor, estimate: Tensor,
                     weak: bool = False) -> int:
        """Add the next keyframe ``j = num_keyframes`` and its odometry edge from keyframe ``i``.

        Args:
            i: an existing keyframe (the front end's reference keyframe).
            T_ij: ``(7,)`` pose of the new keyframe in keyframe ``i``.
            information: ``(6, 6)`` its information.
            estimate: ``(7,)`` the new keyframe's current world pose.
            weak: forced after a tracking loss.

        Returns:
            the new keyframe's id.
        """
        if not 0 <= i < self.num_keyframes:
            raise ValueError(f"odometry edge from keyframe {i}: only {self.num_keyframes} keyframes exist")
        T = _f64(T_ij)
        edge = GraphEdge(i, self.num_keyframes, T, _f64(information), EdgeKind.ODOMETRY, weak=weak)
        # a weak edge measured nothing: a loop may still join its ends
        j = self._append_keyframe(se3_compose(self.odometry_pose(i), T).numpy(), _f64(estimate).numpy(),
                                  self._travelled.view[i] + edge.length,
                                  self._weak_before.view[i] + int(bool(weak)), set() if weak else {i})
        self.edges.append(edge)
        self._chain = self._chain and i == j - 1
        self._new_edge()
        if not weak:
            self._joined[i].add(j)
        return j

    def add_loop(self, i: int, j: int, T_ij: Tensor, information: Tensor) -> int:
        """Add a loop edge between existing keyframes; returns the edge's index in :attr:`edges`."""
        n = self.num_keyframes
        if not (0 <= i < n and 0 <= j < n) or i == j:
            raise ValueError(f"loop edge {i} -> {j}: need two distinct keyframes of {n}")
        self.edges.append(GraphEdge(i, j, _f64(T_ij), _f64(information), EdgeKind.LOOP))
        self._new_edge()
        self._joined[i].add(j)
        self._joined[j].add(i)
        return len(self.edges) - 1

    def _new_edge(self) -> None:
        e = self.edges[-1]
        self._edge_length.append(e.length)
        self._edge_T.append(e.T_ij.numpy())
        self._edge_info.append(e.information.numpy())
        self._edge_ij.append((e.i, e.j))
        self._edge_kind.append(int(e.kind))
        k = len(self.edges) - 1
        for end in (e.i, e.j):
            self._incident[end].append(k)
            (self._loops_of if e.kind is EdgeKind.LOOP else self._odometry_of)[end].append(k)

    def joined(self, k: int) -> set[int]:
        """The keyframes a measured edge (odometry or loop, active or not; not a weak edge, which is a guess)
        joins keyframe ``k`` to: a loop between them would measure again what an edge already holds."""
        if not 0 <= k < self.num_keyframes:
            raise ValueError(f"keyframe {k} out of range for {self.num_keyframes} keyframes")
        return set(self._joined[k])

    def odometry_poses(self) -> Tensor:
        """``(M, 7)`` float64 odometry-chained keyframe poses."""
        return torch.from_numpy(self._odometry.view.copy())

    def estimates(self) -> Tensor:
        """``(M, 7)`` float64 current keyframe pose estimates."""
        return torch.from_numpy(self._estimate.view.copy())

    def estimate(self, k: int) -> Tensor:
        """``(7,)`` current estimate of keyframe ``k``."""
        return torch.from_numpy(self._estimate.view[k].copy())

    def odometry_pose(self, k: int) -> Tensor:
        """``(7,)`` odometry pose of keyframe ``k``."""
        return torch.from_numpy(self._odometry.view[k].copy())

    def set_estimates(self, poses: Tensor) -> None:
        """Replace the estimates of keyframes ``0 .. P-1`` by ``poses (P, 7)`` (P may lag behind new keyframes)."""
        if poses.ndim != 2 or poses.shape[-1] != 7 or poses.shape[0] > self.num_keyframes:
            raise ValueError(f"poses must have shape (P <= {self.num_keyframes}, 7), got {tuple(poses.shape)}")
        self._estimate.view[: poses.shape[0]] = poses.detach().to(torch.float64).cpu().numpy()

    def loop_edges(self, active_only: bool = True) -> List[int]:
        """Indices into :attr:`edges` of the loop edges."""
        return [k for k, e in enumerate(self.edges) if e.kind is EdgeKind.LOOP and (e.active or not active_only)]

    def has_active_loop(self) -> bool:
        """Whether any loop edge is active (searched from the newest loop back)."""
        return any(self.edges[k].active for k in np.flatnonzero(self._edge_kind.view == int(EdgeKind.LOOP))[::-1])

    def pose_graph(self, information_scale: Dict[EdgeKind, float]) -> Optional[PoseGraph]:
        """The :class:`~slam.graph.PoseGraph` over the keyframes at their current estimates.

        Args:
            information_scale: factor on the information of each edge kind (symmetrised after scaling).

        Returns:
            the graph (None when there are no keyframes); its edges are the active ones, in :attr:`edges` order.
        """
        if not len(self._odometry):
            return None
        sel = np.fromiter((k for k, e in enumerate(self.edges) if e.active), np.int64)
        ij = torch.from_numpy(self._edge_ij.view[sel].T.copy())
        return PoseGraph(self.estimates(), ij[0], ij[1], torch.from_numpy(self._edge_T.view[sel]),
                         self._information(sel, information_scale))

    def _information(self, rows: np.ndarray, information_scale: Dict[EdgeKind, float]) -> Tensor:
        """``(e, 6, 6)`` float64 the information of the edges ``rows``, scaled by kind and symmetrised."""
        scale = np.array([float(information_scale[kind]) for kind in EdgeKind])[self._edge_kind.view[rows]]
        info = torch.from_numpy(self._edge_info.view[rows])
        return 0.5 * (info + info.transpose(-1, -2)) * torch.from_numpy(scale)[:, None, None]

    def window_graph(self, information_scale: Dict[EdgeKind, float], free,
                     loops_per_keyframe: Optional[int] = None, fixed=None):
        """The part of the graph that moves the keyframes ``free`` at their current estimates, gathered from them
        alone: the active edges with an end in ``free``, the keyframes they reach outside ``free`` (and those in
        ``fixed``) held as its boundary.

        Args:
            information_scale: as :meth:`pose_graph`.
            free: keyframe ids that may move.
            loops_per_keyframe: at most this many loop edges per free keyframe, the newest (None: all of them).
            fixed: keyframes held even when in ``free``.

        Returns:
            ``(pose graph, keyframe ids of its poses (n,) int64, indices into :attr:`edges` of its edges (e,)
            int64)``, or None when nothing is held (the window has no anchor).

        Raises:
            ValueError: a keyframe of ``free`` is out of range.
        """
        n = self.num_keyframes
        idx = np.unique(np.asarray(list(free), dtype=np.int64))
        if idx.size and (idx[0] < 0 or idx[-1] >= n):
            raise ValueError(f"free keyframe {int(idx[(idx < 0) | (idx >= n)][0])} is not one of the {n} keyframes")
        is_free = np.zeros(n, dtype=bool)
        is_free[idx] = True
        if fixed is not None:
            is_free[np.asarray(list(fixed), dtype=np.int64)] = False
        rows = []
        for k in np.nonzero(is_free)[0].tolist():
            rows.extend(e for e in self._odometry_of[k] if self.edges[e].active)
            # the newest first, stopping at loops_per_keyframe: a place revisited lap after lap holds many
            newest = (e for e in reversed(self._loops_of[k]) if self.edges[e].active)
            rows.extend(itertools.islice(newest, loops_per_keyframe))
        rows = np.unique(np.asarray(rows, dtype=np.int64))
        ij = self._edge_ij.view[rows]
        used = np.unique(np.concatenate([ij.reshape(-1), np.nonzero(is_free)[0]]))
        held = used[~is_free[used]]
        if not held.size:
            return None
        local = np.full(n, -1, dtype=np.int64)
        local[used] = np.arange(used.size)
        P = torch.from_numpy(self._estimate.view[used])
        to = torch.from_numpy
        pg = PoseGraph(P.clone(), to(local[ij[:, 0]]), to(local[ij[:, 1]]), to(self._edge_T.view[rows].copy()),
                       self._information(rows, information_scale), fixed=to(local[held]))
        return pg, to(used), to(rows)

    def edge_kind_codes(self, rows: Tensor) -> Tensor:
        """``(e,)`` int64 :class:`EdgeKind` codes of the edges ``rows`` (indices into :attr:`edges`)."""
        return torch.from_numpy(self._edge_kind.view[rows.numpy()].copy())

    def chain_positions(self, ids) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """Where keyframes lie along the odometry chain: (metres travelled from keyframe 0 ``(k,)`` float64,
        weak edges passed since keyframe 0 ``(k,)`` int64), or None when the odometry edges are no chain; the
        odometry distance of two keyframes is the difference of their metres where their weak counts are equal."""
        idx = np.asarray(ids, dtype=np.int64)
        return (self._travelled.view[idx], self._weak_before.view[idx]) if self._chain else None

    def path_lengths_to(self, source: int, targets, through_loops: bool = True, min_loop_weight: float = 0.0
                        ) -> np.ndarray:
        """:meth:`path_lengths` to ``targets`` only ``(k,)``: the search stops once every target is reached."""
        n = self.num_keyframes
        if not 0 <= source < n:
            raise ValueError(f"source keyframe {source} out of range for {n} keyframes")
        tg = np.asarray(targets, dtype=np.int64).reshape(-1)
        if tg.size and not (0 <= tg.min() and tg.max() < n):
            raise ValueError(f"target keyframes {tg.tolist()} out of range for {n} keyframes")
        if not through_loops and self._chain:
            c, weak = self._travelled.view, self._weak_before.view
            return np.where(weak[tg] == weak[source], np.abs(c[tg] - c[source]), np.inf)
        left = set(tg.tolist())
        dist = {source: 0.0}
        done = set()
        heap = [(0.0, source)]
        lengths = self._edge_length.view
        while heap and left:
            d, u = heapq.heappop(heap)
            if u in done:
                continue
            done.add(u)
            left.discard(u)
            for k in self._incident[u]:
                e = self.edges[k]
                if not e.active:
                    continue
                if e.kind is EdgeKind.ODOMETRY:
                    if e.weak:
                        continue
                elif not (through_loops and e.weight >= min_loop_weight):
                    continue
                v = e.j if e.i == u else e.i
                if v in done:
                    continue
                nd = d + max(float(lengths[k]), 1e-9)  # as path_lengths: an edge is never shorter than 1e-9
                if nd < dist.get(v, math.inf):
                    dist[v] = nd
                    heapq.heappush(heap, (nd, v))
        return np.array([dist.get(int(t), math.inf) for t in tg], dtype=np.float64)

    def path_lengths(self, source: int, through_loops: bool = True, min_loop_weight: float = 0.0) -> np.ndarray:
        """Distance travelled ``(M,)`` (metres) from keyframe ``source`` to every keyframe along the graph.

        Without ``through_loops`` only odometry edges are followed, with it also active loop edges whose back-end
        weight is at least ``min_loop_weight``; weak odometry edges never are. Unreachable keyframes get ``inf``.
        """
        n = self.num_keyframes
        if not 0 <= source < n:
            raise ValueError(f"source keyframe {source} out of range for {n} keyframes")
        if not through_loops and self._chain:
            c, weak = self._travelled.view, self._weak_before.view
            return np.where(weak == weak[source], np.abs(c - c[source]), np.inf)
        use = [e for e in self.edges if e.active and ((e.kind is EdgeKind.ODOMETRY and not e.weak)
                                                      or (e.kind is EdgeKind.LOOP and through_loops
                                                          and e.weight >= min_loop_weight))]
        if not use:
            out = np.full(n, np.inf)
            out[source] = 0.0
            return out
        # a zero-length edge would vanish from a sparse matrix: dijkstra needs explicit positive weights
        w = np.array([max(e.length, 1e-9) for e in use])
        ii = np.array([e.i for e in use])
        jj = np.array([e.j for e in use])
        # parallel edges: coo sums duplicates, so keep the shortest of each pair by hand
        key = np.minimum(ii, jj) * n + np.maximum(ii, jj)
        order = np.lexsort((w, key))
        first = np.ones(len(order), bool)
        first[1:] = key[order][1:] != key[order][:-1]
        sel = order[first]
        A = coo_matrix((w[sel], (ii[sel], jj[sel])), shape=(n, n)).tocsr()
        return dijkstra(A, directed=False, indices=source)
