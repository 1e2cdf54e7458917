"""Group consistency of loops (pairwise consistency maximisation, as in Kimera-RPGO's PCM).

Every verified loop is a hypothesis. Two hypotheses are *consistent* when going round the cycle they form
with the odometry between their ends comes back to the start within the drift that odometry can have
accumulated along those two paths (:func:`slam.loop.acceptance.pairwise_consistent`). True loops agree
with each other; a false loop (an aliased place: an identically furnished room, a repeated texture)
disagrees with the true ones by its own error. The loops kept are the largest set of mutually consistent
hypotheses (a maximum clique of the consistency graph), once it holds at least ``min_group`` loops.

Consistency between two loops far apart along the path says little: the bound on their cycle grows with
the two paths and soon reaches its cap, so a lone wrong loop (a corridor whose repeated texture registers
0.9 m off, seen on the building tour) agrees with every true loop across the building. So a loop is kept
only with *local support* (as ORB-SLAM asks consecutive keyframes to agree): at least ``min_support``
other loops of the group whose ends are both near its own (the two paths summing to at most
``support_radius`` metres), where the pairwise bound is tight. A revisit produces such runs of loops,
keyframe after keyframe; a wrong registration is a one-off.

The checks use the odometry chain only (never the optimised estimate, which the loops themselves bend),
so a wrong loop cannot make itself look consistent. Two loops joined only across a weak edge (a tracking
loss: no measured odometry between their ends) are compared through its guess, within the bound's caps;
with ``compare_across_losses=False`` (``LoopClosureConfig.recover_after_loss``) they are not compared and
count as consistent, as PCM compares only loops that odometry joins. Loops across the same loss are
compared either way (their ends lie on the same sides of it), so a run of true loops mending a loss still
outvotes a wrong one.

Cost per loop independent of the run's length: a new loop is compared, in one batched computation, with
the loops it can disagree with. While there are at most ``max_exact`` hypotheses that is every earlier one
(the group is their exact maximum clique). Beyond, the group grows greedily (a new loop joins it when it
agrees with it) and only the group's loops whose two ends both lie within the *capped length* of the new
loop's along the odometry chain are compared (:func:`slam.loop.acceptance.capped_length`, 27 m with the
defaults: from there on the bound is its caps, and comparing farther loops measures the odometry's drift
rather than the loop: tests/slam/loop/test_consistency_vectorised.py). The loops compared are a suffix of
the group (ordered by their newer end, which only moves forward), found by bisection; loops joined across a
tracking loss are compared through the guess as before. Pairwise results are kept sparse (the pairs that
disagree, the pairs near enough to support each other): no matrix grows with the run.

Example:
    >>> import torch
    >>> from slam.lie import se3_exp, se3_identity
    >>> from slam.keyframe_graph import KeyframeGraph
    >>> g = KeyframeGraph()
    >>> step = se3_exp(torch.tensor([0.3, 0, 0, 0, 0, 0], dtype=torch.float64))
    >>> _ = g.add_keyframe(se3_identity(dtype=torch.float64))
    >>> for k in range(1, 6):
    ...     _ = g.add_odometry(k - 1, step, torch.eye(6, dtype=torch.float64), g.odometry_pose(k - 1))
    >>> check = GroupConsistency(ConsistencyConfig())
    >>> check.add(0, 4, se3_exp(torch.tensor([1.2, 0, 0, 0, 0, 0], dtype=torch.float64)), g)  # alone: held
    []
    >>> check.add(1, 5, se3_exp(torch.tensor([1.2, 0, 0, 0, 0, 0], dtype=torch.float64)), g)
    [0, 1]
    >>> check.add(0, 5, se3_exp(torch.tensor([0.1, 2.0, 0, 0, 0, 0], dtype=torch.float64)), g)  # false
    [0, 1]
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from slam.keyframe_graph import GrowingArray, KeyframeGraph
from slam.lie import se3_between
from slam.loop.acceptance import DriftBoundConfig, capped_length, drift_limits_array, pairwise_errors
from slam.odometry.config import check_int, check_number  # the configs' shared range checks

Tensor = torch.Tensor

__all__ = ["ConsistencyConfig", "GroupConsistency", "maximum_clique"]


@dataclass(frozen=True)
class ConsistencyConfig:
    """Settings of :class:`GroupConsistency`."""

    enabled: bool = True  # False: every verified loop is kept
    # A group needs this many mutually consistent loops before any of them is kept.
    min_group: int = 1
    # Local support: a kept loop needs this many other loops of the group whose two ends are within
    # support_radius metres (the sum of the two paths along the odometry chain) of its own. 0: off.
    min_support: int = 1
    support_radius: float = 2.0  # m
    # The pairwise bound: the drift bound of slam.loop.acceptance on the summed length of the two paths.
    bound: DriftBoundConfig = field(default_factory=DriftBoundConfig)
    # Exact maximum clique up to this many hypotheses; beyond, a new one joins the group when it agrees with
    # the group's loops near it (while there is no group: the exact clique of the newest max(max_exact, min_group)).
    max_exact: int = 400

    def __post_init__(self) -> None:
        for name, least in (("min_group", 1), ("min_support", 0), ("max_exact", 0)):
            check_int("ConsistencyConfig", name, getattr(self, name), least)
        check_number("ConsistencyConfig", "support_radius", self.support_radius, 0, finite=True)


def maximum_clique(adjacency: np.ndarray) -> list[int]:
    """A maximum clique of an undirected graph (branch and bound over Bron-Kerbosch with pivoting).

    Deterministic: vertices are tried in increasing order and the first largest clique found is kept; a
    candidate set that is itself a clique ends its branch at once.

    Args:
        adjacency: ``(n, n)`` bool, symmetric; the diagonal is ignored.

    Returns:
        the clique's vertices, sorted.
    """
    A = np.asarray(adjacency, bool)
    n = A.shape[0]
    if A.ndim != 2 or A.shape != (n, n):
        raise ValueError(f"adjacency must be square, got {A.shape}")
    A = A & A.T
    np.fill_diagonal(A, False)
    packed = np.packbits(A, axis=1, bitorder="little")  # row u: bit v set when u and v are adjacent
    nbrs = [int.from_bytes(row.tobytes(), "little") for row in packed]
    best: list[int] = []
    best_size = 0

    def members(mask: int) -> list[int]:
        out = []
        while mask:
            low = mask & -mask
            out.append(low.bit_length() - 1)
            mask ^= low
        return out

    def expand(R: list[int], P: int) -> None:
        nonlocal best, best_size
        size = P.bit_count()
        if len(R) + size <= best_size:
            return  # cannot beat the best clique found so far
        if not P:
            best, best_size = sorted(R), len(R)
            return
        verts = members(P)
        if all(nbrs[u] & P == P ^ (1 << u) for u in verts):  # P is a clique: the branch ends in R + P
            best, best_size = sorted(R + verts), len(R) + size
            return
        pivot = max(verts, key=lambda u: (nbrs[u] & P).bit_count())
        for v in members(P & ~nbrs[pivot]):
            expand(R + [v], P & nbrs[v])
            P &= ~(1 << v)

    expand([], (1 << n) - 1)
    return best


class GroupConsistency:
    """The loops kept so far by pairwise consistency maximisation; hypotheses are numbered as added.

    Args:
        config: :class:`ConsistencyConfig`.
        compare_across_losses: compare two loops joined only across a weak edge through its guess (within the
            caps); False: they count as consistent (``LoopClosureConfig.recover_after_loss``).
    """

    def __init__(self, config: ConsistencyConfig, compare_across_losses: bool = True):
        self.config = config
        self.compare_across_losses = compare_across_losses
        # per hypothesis: its ends, measured pose, the ends' odometry poses and chain positions (metres
        # travelled, weak edges passed: NaN / -1 where the graph is no chain)
        self._ends = GrowingArray(np.int64, (2,))
        self._Z = GrowingArray(np.float64, (7,))
        self._odo = GrowingArray(np.float64, (2, 7))
        self._pos = GrowingArray(np.float64, (2,))
        self._seg = GrowingArray(np.int64, (2,))
        self._disagree: list[np.ndarray] = []  # per hypothesis: the earlier ones found inconsistent with it
        self._supports: list[np.ndarray] = []  # per hypothesis: the earlier ones consistent with it and near
        self._in_group = GrowingArray(bool)
        self._is_kept = GrowingArray(bool)
        self._support = GrowingArray(np.int64)  # per group member: the members near it that agree with it
        self._group: list[int] = []  # the largest mutually consistent set, sorted (ids, so newer ends last)
        self._group_b = GrowingArray(np.float64)  # the group's newer ends' chain positions, in group order
        self._reach = max(capped_length(config.bound), config.support_radius)

    def __len__(self) -> int:
        return len(self._ends)

    @property
    def kept(self) -> list[int]:
        """Indices of the hypotheses kept now (sorted)."""
        return np.flatnonzero(self._is_kept.view).tolist()

    def is_kept(self, i: int) -> bool:
        """Whether hypothesis ``i`` is kept now."""
        return bool(self._is_kept.view[i])

    @property
    def adjacency(self) -> np.ndarray:
        """``(n, n)`` bool pairwise consistency of the hypotheses so far (a pair never compared: True)."""
        return self._dense(0, len(self))

    def _dense(self, start: int, stop: int) -> np.ndarray:
        """``(m, m)`` bool consistency among hypotheses ``start .. stop - 1`` (never-compared pairs True)."""
        m = stop - start
        A = np.ones((m, m), bool)
        for i in range(start, stop):
            d = self._disagree[i]
            d = d[d >= start] - start
            A[i - start, d] = A[d, i - start] = False
        return A

    def _compare(self, new: int, others: np.ndarray, graph: KeyframeGraph) -> tuple[np.ndarray, np.ndarray]:
        """Whether hypothesis ``new`` agrees with each of ``others`` ``(k,)`` (earlier ids), and the pairs'
        odometry path lengths: ``((k,) bool, (k,) float64 metres, inf across a weak edge)``, batched."""
        if others.size == 0:
            return np.zeros(0, bool), np.zeros(0)
        ends = self._ends.view
        if np.isnan(self._pos.view[new, 0]):  # no chain: the odometry distances from the new loop's two ends
            la = graph.path_lengths(int(ends[new, 0]), through_loops=False)
            lb = graph.path_lengths(int(ends[new, 1]), through_loops=False)
            L = la[ends[others, 0]] + lb[ends[others, 1]]
        else:
            pos, seg = self._pos.view, self._seg.view
            same = (seg[others] == seg[new]).all(axis=1)
            gaps = np.abs(pos[others] - pos[new]).sum(axis=1)
            L = np.where(same, gaps, np.inf)
        ok = np.ones(others.size, bool)
        look = np.isfinite(L) | self.compare_across_losses  # across a loss, without comparing: consistent
        if look.any():
            o = others[look]
            Z = torch.from_numpy(self._Z.view)
            odo = torch.from_numpy(self._odo.view)
            dt, dr = pairwise_errors(Z[o], Z[new], se3_between(odo[o, 0], odo[new, 0]),
                                     se3_between(odo[o, 1], odo[new, 1]))
            t_lim, r_lim = drift_limits_array(L[look], self.config.bound)
            ok[look] = (dt.numpy() <= t_lim) & (dr.numpy() <= r_lim)
        return ok, L

    def _neighbourhood(self, new: int) -> np.ndarray:
        """The group's loops that can disagree with hypothesis ``new`` beyond the caps' reach (sorted ids)."""
        g = np.asarray(self._group, dtype=np.int64)
        if np.isnan(self._pos.view[new, 0]) or not math.isfinite(self._reach):
            return g  # no chain positions (or a bound that never caps): the whole group
        pos, seg = self._pos.view, self._seg.view
        lo = int(np.searchsorted(self._group_b.view, pos[new, 1] - self._reach, side="left"))
        near = g[lo:]
        near = near[np.abs(pos[near, 0] - pos[new, 0]) <= self._reach]
        if self.compare_across_losses and seg[new, 1] > 0:
            # loops whose ends lie across a weak edge from the new one's: compared through the guess
            across = g[(seg[g] != seg[new]).any(axis=1)]
            near = np.union1d(near, across)
        return near

    def add(self, a: int, b: int, T_ab: Tensor, graph: KeyframeGraph) -> list[int]:
        """Add the hypothesis ``a -> b`` measuring ``T_ab`` (pose of b in a); returns the kept hypotheses.

        Args:
            a, b: keyframe ids (both in ``graph``).
            T_ab: ``(7,)`` the loop's measured relative pose.
            graph: the keyframe graph (its odometry poses and path lengths).
        """
        self.update(a, b, T_ab, graph)
        return self.kept

    def update(self, a: int, b: int, T_ab: Tensor, graph: KeyframeGraph) -> list[int]:
        """:meth:`add`, returning instead the hypotheses whose kept state changed (the new one when kept)."""
        new = len(self)
        self._ends.append((int(a), int(b)))
        self._Z.append(T_ab.detach().to(torch.float64).cpu().numpy())
        if graph is not None:
            self._odo.append(np.stack([graph.odometry_pose(int(a)).numpy(), graph.odometry_pose(int(b)).numpy()]))
            chain = graph.chain_positions([int(a), int(b)])
        else:  # a subclass that compares by other means
            self._odo.append(np.zeros((2, 7)))
            chain = None
        self._pos.append(chain[0] if chain is not None else (np.nan, np.nan))
        self._seg.append(chain[1] if chain is not None else (-1, -1))
        for col in (self._in_group, self._is_kept):
            col.append(False)
        self._support.append(0)
        cfg = self.config
        if not cfg.enabled:
            self._disagree.append(np.zeros(0, np.int64))
            self._supports.append(np.zeros(0, np.int64))
            self._in_group.view[new] = True
            self._group.append(new)
            self._group_b.append(self._pos.view[new, 1])
            return self._set_kept(np.array([new]))
        n = new + 1
        window = max(cfg.max_exact, cfg.min_group)
        if n <= cfg.max_exact:
            others = np.arange(new, dtype=np.int64)
        elif self._group:
            others = self._neighbourhood(new)
        else:  # no group: the exact clique of the newest hypotheses is sought
            others = np.arange(max(0, n - window), new, dtype=np.int64)
        ok, L = self._compare(new, others, graph)
        self._disagree.append(others[~ok])
        self._supports.append(others[ok & (L <= cfg.support_radius)])
        if self._group and n > cfg.max_exact:  # greedy: the newest joins the group if it agrees with all of it
            return self._join(new) if ok.all() else []
        start = 0 if n <= cfg.max_exact else max(0, n - window)
        clique = [start + k for k in maximum_clique(self._dense(start, n))]
        return self._set_group(clique if len(clique) >= cfg.min_group else [])

    def _set_group(self, group: list[int]) -> list[int]:
        """A new group (exact phase): the support counted again among its loops; returns the changes."""
        in_group = self._in_group.view
        in_group[:] = False
        in_group[group] = True
        self._group = list(group)
        self._group_b = GrowingArray(np.float64)
        for k in self._group:
            self._group_b.append(self._pos.view[k, 1])
        support = self._support.view
        support[:] = 0
        for j in self._group:
            s = self._supports[j]
            s = s[in_group[s]]
            support[s] += 1
            support[j] += s.size
        keep = in_group & (support >= self.config.min_support) if self.config.min_support > 0 else in_group.copy()
        return self._set_kept(np.flatnonzero(keep != self._is_kept.view))

    def _join(self, new: int) -> list[int]:
        """The newest hypothesis joins the group (greedy phase): only its supporters' counts change."""
        self._in_group.view[new] = True
        self._group.append(new)
        self._group_b.append(self._pos.view[new, 1])
        s = self._supports[new]
        s = s[self._in_group.view[s]]
        support = self._support.view
        support[s] += 1
        support[new] = s.size
        touched = np.append(s, new)
        need = self.config.min_support
        keep = support[touched] >= need if need > 0 else np.ones(touched.size, bool)
        return self._set_kept(touched[keep != self._is_kept.view[touched]])

    def _set_kept(self, flip: np.ndarray) -> list[int]:
        """Flip the kept state of ``flip``; returns them as a sorted list."""
        flip = np.unique(np.asarray(flip, dtype=np.int64))
        kept = self._is_kept.view
        kept[flip] = ~kept[flip]
        return flip.tolist()
