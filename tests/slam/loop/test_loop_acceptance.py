"""Loop acceptance: the drift bound, pairwise consistency, the maximum clique and the group check."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from slam.keyframe_graph import EdgeKind, KeyframeGraph
from slam.lie import se3_between, se3_compose, se3_exp, se3_identity
from slam.loop.acceptance import DriftBoundConfig, drift_limits, pairwise_consistent
from slam.loop.consistency import ConsistencyConfig, GroupConsistency, maximum_clique

D = torch.float64


def _T(x=0.0, y=0.0, z=0.0, yaw=0.0):
    return se3_exp(torch.tensor([x, y, z, 0.0, 0.0, yaw], dtype=D))


def test_bound_grows_with_distance_travelled():
    """The acceptance bound is affine in the distance travelled, capped; never one fixed value."""
    cfg = DriftBoundConfig()
    lengths = [0.0, 0.5, 2.0, 5.0, 10.0, 1e3, math.inf]
    lim = [drift_limits(L, cfg) for L in lengths]
    assert lim[0].translation == pytest.approx(cfg.translation_base)
    assert lim[0].rotation_deg == pytest.approx(cfg.rotation_base_deg)
    assert lim[2].translation == pytest.approx(cfg.translation_base + 2.0 * cfg.translation_per_metre)
    assert lim[3].rotation_deg == pytest.approx(cfg.rotation_base_deg + 5.0 * cfg.rotation_per_metre_deg)
    t = [x.translation for x in lim]
    r = [x.rotation_deg for x in lim]
    assert all(b >= a for a, b in zip(t, t[1:])) and t[3] > t[1] > t[0]
    assert all(b >= a for a, b in zip(r, r[1:])) and r[3] > r[1] > r[0]
    assert t[-2] == t[-1] == cfg.max_translation and r[-1] == cfg.max_rotation_deg
    with pytest.raises(ValueError):
        drift_limits(-1.0, cfg)
    with pytest.raises(ValueError):
        DriftBoundConfig(translation_per_metre=-0.1)


def test_bound_follows_the_graph_distance():
    """Without loops the distance is the odometry chain's; a loop in the graph is a shortcut."""
    g = KeyframeGraph()
    g.add_keyframe(se3_identity(dtype=D))
    for k in range(1, 11):  # 10 steps of 0.5 m
        g.add_odometry(k - 1, _T(0.5), torch.eye(6, dtype=D), se3_compose(g.estimate(k - 1), _T(0.5)))
    chain = g.path_lengths(10, through_loops=False)
    assert chain[0] == pytest.approx(5.0) and chain[10] == 0.0
    e = g.add_loop(2, 10, _T(4.0), torch.eye(6, dtype=D))
    assert g.path_lengths(10, through_loops=False)[0] == pytest.approx(5.0)
    assert g.path_lengths(10, through_loops=True)[0] == pytest.approx(4.0 + 1.0)
    g.edges[e].weight = 0.01  # switched off by the back end: no shortcut above the weight floor
    assert g.path_lengths(10, through_loops=True, min_loop_weight=0.1)[0] == pytest.approx(5.0)
    g.edges[e].active = False
    assert g.path_lengths(10, through_loops=True)[0] == pytest.approx(5.0)
    # the Dijkstra path and the chain shortcut agree
    assert np.allclose(g.path_lengths(3, through_loops=True), g.path_lengths(3, through_loops=False))
    bound = DriftBoundConfig()
    assert drift_limits(chain[0], bound).translation > drift_limits(chain[8], bound).translation


def test_pairwise_consistency_of_exact_and_wrong_loops():
    """Two loops measured from the true poses close their cycle exactly; a loop off by 1 m does not."""
    P = [_T(0, 0), _T(1.0, 0.2, yaw=0.3), _T(5.0, 3.0, yaw=2.0), _T(5.6, 3.1, yaw=2.2)]
    a1, a2, b1, b2 = 0, 1, 2, 3
    Z1, Z2 = se3_between(P[a1], P[b1]), se3_between(P[a2], P[b2])
    ok, dt, dr = pairwise_consistent(Z1, Z2, se3_between(P[a1], P[a2]), se3_between(P[b1], P[b2]),
                                     drift_limits(0.0, DriftBoundConfig()))
    assert ok and dt < 1e-9 and dr < 1e-6
    wrong = se3_compose(Z2, _T(1.0))
    ok, dt, dr = pairwise_consistent(Z1, wrong, se3_between(P[a1], P[a2]), se3_between(P[b1], P[b2]),
                                     drift_limits(0.0, DriftBoundConfig()))
    assert not ok and dt == pytest.approx(1.0, abs=1e-9)
    # the same error is tolerated after enough distance travelled (it could be drift)
    ok, _, _ = pairwise_consistent(Z1, wrong, se3_between(P[a1], P[a2]), se3_between(P[b1], P[b2]),
                                   drift_limits(30.0, DriftBoundConfig()))
    assert ok


def test_maximum_clique_matches_brute_force():
    rng = np.random.default_rng(0)
    for _ in range(150):
        n = int(rng.integers(0, 10))
        A = rng.random((n, n)) < rng.uniform(0.2, 0.9)
        A = A | A.T
        c = maximum_clique(A)
        assert all(A[i, j] for i, j in itertools.combinations(c, 2))
        best = 0
        for k in range(n, 0, -1):
            if any(all(A[i, j] for i, j in itertools.combinations(S, 2)) for S in itertools.combinations(range(n), k)):
                best = k
                break
        assert len(c) == best
    assert maximum_clique(np.zeros((0, 0), bool)) == []
    with pytest.raises(ValueError):
        maximum_clique(np.zeros((2, 3), bool))


def _corridor_graph(n=30, step=0.3):
    g = KeyframeGraph()
    g.add_keyframe(se3_identity(dtype=D))
    for k in range(1, n):
        g.add_odometry(k - 1, _T(step), torch.eye(6, dtype=D), se3_compose(g.estimate(k - 1), _T(step)))
    return g


def test_group_consistency_keeps_the_consistent_group_and_drops_a_false_loop():
    g = _corridor_graph()
    truth = [g.odometry_pose(k) for k in range(g.num_keyframes)]
    check = GroupConsistency(ConsistencyConfig())
    for a, b in ((0, 20), (1, 21), (2, 22)):
        check.add(a, b, se3_compose(se3_between(truth[a], truth[b]), _T(0.02)), g)
    assert check.kept == [0, 1, 2]
    # an aliased place: measured 0.3 m from keyframe 3 while odometry puts it 7 m away
    kept = check.add(3, 26, _T(0.3, yaw=0.1), g)
    assert kept == [0, 1, 2] and not check.adjacency[3, :3].any()
    # a group of two false loops agreeing with each other is still the smaller group
    Z4 = se3_compose(se3_compose(se3_between(truth[4], truth[3]), _T(0.3, yaw=0.1)), se3_between(truth[26], truth[27]))
    kept = check.add(4, 27, Z4, g)
    assert kept == [0, 1, 2] and check.adjacency[3, 4]


def test_group_consistency_min_group_and_disabled():
    g = _corridor_graph()
    truth = [g.odometry_pose(k) for k in range(g.num_keyframes)]
    check = GroupConsistency(ConsistencyConfig(min_group=2))
    assert check.add(0, 20, se3_between(truth[0], truth[20]), g) == []  # a lone loop waits for a second
    assert check.add(1, 21, se3_between(truth[1], truth[21]), g) == [0, 1]
    off = GroupConsistency(ConsistencyConfig(enabled=False))
    off.add(0, 20, se3_between(truth[0], truth[20]), g)
    assert off.add(3, 26, _T(0.3), g) == [0, 1]


def test_a_lone_loop_waits_for_local_support():
    """Far apart along the path, the pairwise bound reaches ~1 m: a lone loop 0.6 m wrong agrees with the
    true ones across the graph and joins the largest group. Local support holds it out: no other loop has
    both ends near its own. A true loop beside it disagrees with it (short paths: a tight bound), so the
    true pair forms the group and is kept once the second of them arrives."""
    g = _corridor_graph(n=60, step=0.5)
    truth = [g.odometry_pose(k) for k in range(g.num_keyframes)]
    cfg = ConsistencyConfig()
    assert cfg.min_support == 1 and cfg.support_radius == 2.0
    check, old = GroupConsistency(cfg), GroupConsistency(ConsistencyConfig(min_support=0))
    for a, b in ((0, 40), (1, 41), (2, 42)):
        for c in (check, old):
            c.add(a, b, se3_between(truth[a], truth[b]), g)
    wrong = se3_compose(se3_between(truth[20], truth[55]), _T(0.6))
    assert old.add(20, 55, wrong, g) == [0, 1, 2, 3]  # without local support it is kept
    assert check.add(20, 55, wrong, g) == [0, 1, 2]
    assert check.adjacency[3, :3].all()  # consistent with the far group: the loose bound lets it in
    # a true loop beside it: inconsistent with it; alone on its side of the graph it waits too
    assert check.add(21, 56, se3_between(truth[21], truth[56]), g) == [0, 1, 2]
    assert not check.adjacency[3, 4]
    assert check.add(22, 57, se3_between(truth[22], truth[57]), g) == [0, 1, 2, 4, 5]
    with pytest.raises(ValueError, match="min_support"):
        ConsistencyConfig(min_support=-1)
    with pytest.raises(ValueError, match="support_radius"):
        ConsistencyConfig(support_radius=math.inf)


def test_keyframe_graph_pose_graph_scales_by_kind():
    g = _corridor_graph(4)
    g.add_loop(0, 3, _T(0.9), 2.0 * torch.eye(6, dtype=D))
    pg = g.pose_graph({EdgeKind.ODOMETRY: 0.5, EdgeKind.LOOP: 0.01})
    assert pg.num_edges == 4 and g.edge_kind_codes(torch.arange(4)).tolist() == [0, 0, 0, 1]
    assert torch.allclose(pg.information[0], 0.5 * torch.eye(6, dtype=D))
    assert torch.allclose(pg.information[3], 0.02 * torch.eye(6, dtype=D))
    g.edges[3].active = False
    assert g.pose_graph({EdgeKind.ODOMETRY: 1.0, EdgeKind.LOOP: 1.0}).num_edges == 3
    assert g.loop_edges() == [] and g.loop_edges(active_only=False) == [3]
    with pytest.raises(ValueError):
        g.add_loop(0, 0, _T(), torch.eye(6, dtype=D))
    with pytest.raises(ValueError):
        g.add_odometry(7, _T(), torch.eye(6, dtype=D), _T())
    with pytest.raises(ValueError):
        g.set_estimates(torch.zeros(9, 7, dtype=D))


class _GivenConsistency(GroupConsistency):
    """Group consistency over a given pairwise-consistency matrix (every pair near: local support is off)."""

    def __init__(self, config, adjacency):
        super().__init__(config)
        self._given = np.asarray(adjacency, bool)

    def _compare(self, new, others, graph):
        return self._given[others, new].copy(), np.zeros(others.size)


def _kept_after_each(config, adjacency):
    check = _GivenConsistency(config, adjacency)
    return [check.add(k, k + 1, torch.zeros(7, dtype=torch.float64), None) for k in range(len(adjacency))]


@pytest.mark.parametrize("max_exact", [0, 1, 2, 400])
def test_min_group_holds_beyond_the_exact_clique_size(max_exact):
    # past max_exact the group grows greedily; while it is empty it is the exact clique of the newest
    # hypotheses, and min_group applies there too (the greedy rule once admitted a lone loop as a group)
    cfg = ConsistencyConfig(min_group=3, min_support=0, max_exact=max_exact)
    agree = np.ones((5, 5), bool)
    assert _kept_after_each(cfg, agree) == [[], [], [0, 1, 2], [0, 1, 2, 3], [0, 1, 2, 3, 4]]
    lone = np.eye(5, dtype=bool)  # nothing agrees with anything: never a group
    assert _kept_after_each(ConsistencyConfig(min_group=2, min_support=0, max_exact=max_exact), lone) == [[]] * 5
    # a false loop (2) in a run of true ones: the true ones are kept, the false one never joins
    mixed = np.ones((5, 5), bool)
    mixed[2, :] = mixed[:, 2] = False
    mixed[2, 2] = True
    got = _kept_after_each(ConsistencyConfig(min_group=2, min_support=0, max_exact=max_exact), mixed)
    assert got[-1] == [0, 1, 3, 4] and all(2 not in kept for kept in got)
