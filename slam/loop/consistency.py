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

from slam.keyframe_graph import KeyframeGraph
from slam.lie import se3_between
from slam.loop.acceptance import DriftBoundConfig, drift_limits, pairwise_consistent
from slam.odometry.config import check_int  # the configs' shared range check

Tensor = torch.Tensor

__all__ = ["ConsistencyConfig", "GroupConsistency", "maximum_clique"]


@dataclass(frozen=True)
class ConsistencyConfig:
    """Settings of :class:`GroupConsistency`."""

    enabled: bool = True  # False: every verified loop is kept
    # A group needs this many mutually consistent loops before any of them is kept (1: any group; each
    # of its loops still needs local support, below).
    min_group: int = 1
    # Local support (module docstring): a kept loop needs this many other loops of the group whose two ends
    # are within support_radius metres (the sum of the two paths along the odometry chain) of its own. 0:
    # off. The loops of a revisit come keyframe after keyframe (on the building tour: query keyframes
    # 3-13 frames apart).
    min_support: int = 1
    support_radius: float = 2.0  # m
    # The pairwise bound: the drift bound of slam.loop.acceptance on the summed length of the two paths.
    bound: DriftBoundConfig = field(default_factory=DriftBoundConfig)
    # Exact maximum clique up to this many hypotheses; beyond, the newest ones are checked greedily
    # against the kept group (bounds the cost on very long runs), and while there is no group, the group
    # is the exact clique of the newest max(max_exact, min_group) hypotheses.
    max_exact: int = 400

    def __post_init__(self) -> None:
        for name, least in (("min_group", 1), ("min_support", 0), ("max_exact", 0)):
            check_int("ConsistencyConfig", name, getattr(self, name), least)
        if not (self.support_radius >= 0 and math.isfinite(self.support_radius)):
            raise ValueError(f"ConsistencyConfig.support_radius must be finite and >= 0, got {self.support_radius!r}")


def maximum_clique(adjacency: np.ndarray) -> list[int]:
    """A maximum clique of an undirected graph (branch and bound over Bron-Kerbosch with pivoting).

    Deterministic: vertices are tried in increasing order and the first largest clique found is kept.

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
    nbrs = [set(np.flatnonzero(A[i]).tolist()) for i in range(n)]
    best: list[int] = []

    def expand(R: list[int], P: set) -> None:
        nonlocal best
        if len(R) + len(P) <= len(best):
            return  # cannot beat the best clique found so far
        if not P:
            best = sorted(R)
            return
        pivot = max(sorted(P), key=lambda u: len(nbrs[u] & P))
        for v in sorted(P - nbrs[pivot]):
            expand(R + [v], P & nbrs[v])
            P = P - {v}

    expand([], set(range(n)))
    return best


class GroupConsistency:
    """The loops kept so far by pairwise consistency maximisation (see the module docstring).

    Hypotheses are numbered in the order they are added; :meth:`add` returns the kept ones.
    """

    def __init__(self, config: ConsistencyConfig, compare_across_losses: bool = True):
        """
        Args:
            config: :class:`ConsistencyConfig`.
            compare_across_losses: compare two loops joined only across a weak edge through its guess
                (within the caps); False: they count as consistent (``LoopClosureConfig.recover_after_loss``).
        """
        self.config = config
        self.compare_across_losses = compare_across_losses  # False: loops a loss separates are not compared
        self._loops: list[tuple[int, int, Tensor]] = []
        self._adj = np.zeros((0, 0), bool)
        self._near = np.zeros((0, 0), bool)  # the two ends within support_radius of each other's
        self._group: list[int] = []  # the largest mutually consistent set
        self._kept: list[int] = []  # those of it with local support

    @property
    def kept(self) -> list[int]:
        """Indices of the hypotheses kept now (sorted)."""
        return list(self._kept)

    @property
    def adjacency(self) -> np.ndarray:
        """``(n, n)`` bool pairwise consistency of the hypotheses so far."""
        return self._adj.copy()

    def _consistent(self, i: int, j: int, graph: KeyframeGraph, lengths: dict) -> tuple[bool, float]:
        a1, b1, Z1 = self._loops[i]
        a2, b2, Z2 = self._loops[j]
        odo = graph.odometry_pose

        def length(u: int, v: int) -> float:
            if u not in lengths:
                lengths[u] = graph.path_lengths(u, through_loops=False)
            return float(lengths[u][v])

        L = length(a1, a2) + length(b1, b2)
        if not math.isfinite(L) and not self.compare_across_losses:
            # a path crosses a weak edge (a tracking loss): odometry says nothing about how the two loops
            # relate, so they cannot contradict each other (PCM compares only loops joined by odometry)
            return True, L
        ok, _, _ = pairwise_consistent(Z1, Z2, se3_between(odo(a1), odo(a2)), se3_between(odo(b1), odo(b2)),
                                       drift_limits(L, self.config.bound))
        return ok, L

    def add(self, a: int, b: int, T_ab: Tensor, graph: KeyframeGraph) -> list[int]:
        """Add the hypothesis ``a -> b`` measuring ``T_ab`` (pose of b in a); returns the kept hypotheses.

        Args:
            a, b: keyframe ids (both in ``graph``).
            T_ab: ``(7,)`` the loop's measured relative pose.
            graph: the keyframe graph (its odometry poses and odometry path lengths are used).
        """
        self._loops.append((int(a), int(b), T_ab.detach().to(torch.float64).cpu()))
        n = len(self._loops)
        adj = np.zeros((n, n), bool)
        adj[:n - 1, :n - 1] = self._adj
        near = np.zeros((n, n), bool)
        near[:n - 1, :n - 1] = self._near
        lengths: dict = {}
        for i in range(n - 1):
            ok, L = self._consistent(i, n - 1, graph, lengths)
            adj[i, n - 1] = adj[n - 1, i] = ok
            near[i, n - 1] = near[n - 1, i] = L <= self.config.support_radius
        self._adj, self._near = adj, near
        if not self.config.enabled:
            self._group = self._kept = list(range(n))
            return list(self._kept)
        if n <= self.config.max_exact:
            clique = maximum_clique(adj)
            self._group = clique if len(clique) >= self.config.min_group else []
        elif self._group:  # greedy beyond the exact size: the newest joins the group if it agrees with all of it
            if all(adj[k, n - 1] for k in self._group):
                self._group = sorted(self._group + [n - 1])
        else:
            # no group yet: the exact clique of the newest hypotheses, as many as max_exact (at least
            # min_group), so that min_group holds here too and the cost stays bounded
            start = max(0, n - max(self.config.max_exact, self.config.min_group))
            clique = [start + k for k in maximum_clique(adj[start:, start:])]
            self._group = clique if len(clique) >= self.config.min_group else []
        g = np.asarray(self._group, dtype=np.int64)
        if self.config.min_support > 0 and g.size:
            support = (adj & near)[np.ix_(g, g)].sum(axis=1)  # the diagonal is False
            self._kept = g[support >= self.config.min_support].tolist()
        else:
            self._kept = list(self._group)
        return list(self._kept)
