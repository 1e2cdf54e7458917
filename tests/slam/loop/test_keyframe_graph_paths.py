"""KeyframeGraph.path_lengths_to: the distances of path_lengths (scipy's Dijkstra over the whole graph) to
chosen keyframes, by a search that stops at them; chain positions; the growing arrays behind them."""
from __future__ import annotations

import random

import numpy as np
import pytest
import torch

from slam.keyframe_graph import EdgeKind, GrowingArray, KeyframeGraph
from slam.lie import se3_compose, se3_exp, se3_identity

D = torch.float64


def _random_graph(seed):
    r = random.Random(seed)
    gen = torch.Generator().manual_seed(seed)
    g = KeyframeGraph()
    g.add_keyframe(se3_identity(dtype=D))
    n = r.randint(2, 60)
    for k in range(1, n):
        T = se3_exp(0.3 * torch.randn(6, generator=gen, dtype=D))
        g.add_odometry(k - 1, T, torch.eye(6, dtype=D), se3_compose(g.odometry_pose(k - 1), T), weak=r.random() < 0.05)
    for _ in range(r.randint(0, 40)):
        i, j = r.sample(range(n), 2)
        e = g.add_loop(i, j, se3_exp(0.5 * torch.randn(6, generator=gen, dtype=D)), torch.eye(6, dtype=D))
        g.edges[e].active = r.random() > 0.2
        g.edges[e].weight = r.random()
    return g, r


@pytest.mark.parametrize("seed", range(12))
def test_path_lengths_to_equals_the_full_search(seed):
    g, r = _random_graph(seed)
    n = g.num_keyframes
    for through_loops in (True, False):
        for weight in (0.0, 0.5):
            source = r.randrange(n)
            targets = [r.randrange(n) for _ in range(6)]
            want = g.path_lengths(source, through_loops=through_loops, min_loop_weight=weight)[targets]
            got = g.path_lengths_to(source, targets, through_loops=through_loops, min_loop_weight=weight)
            assert np.array_equal(got, want)  # the same sums in the same order: equal to the bit
    assert g.path_lengths_to(0, []).shape == (0,)
    with pytest.raises(ValueError, match="target"):
        g.path_lengths_to(0, [n])
    with pytest.raises(ValueError, match="source"):
        g.path_lengths_to(n, [0])


def test_chain_positions_give_the_chain_distances():
    g = KeyframeGraph()
    g.add_keyframe(se3_identity(dtype=D))
    steps = [0.5, 0.25, 1.0, 0.75]
    for k, s in enumerate(steps, 1):
        T = se3_exp(torch.tensor([s, 0, 0, 0, 0, 0], dtype=D))
        g.add_odometry(k - 1, T, torch.eye(6, dtype=D), se3_compose(g.odometry_pose(k - 1), T), weak=k == 3)
    c, w = g.chain_positions([0, 1, 2, 3, 4])
    assert c.tolist() == pytest.approx([0.0, 0.5, 0.75, 1.75, 2.5]) and w.tolist() == [0, 0, 0, 1, 1]
    assert g.path_lengths(4, through_loops=False)[3] == pytest.approx(0.75)
    assert np.isinf(g.path_lengths(4, through_loops=False)[2])


def test_growing_array_keeps_its_rows():
    a = GrowingArray(np.int64, (2,))
    for k in range(100):
        a.append((k, -k))
    assert len(a) == 100 and a.view[:, 0].tolist() == list(range(100)) and a.view[57, 1] == -57


@pytest.mark.parametrize("seed", range(8))
def test_window_graph_gathers_the_window_edges_of_the_whole_graph(seed):
    """The subgraph gathered from the window's keyframes against the edges picked from the whole list by hand:
    every active edge with a free end (of each free keyframe's loops the newest ``cap`` active ones), their
    measurements, the information symmetrised and scaled by kind, the poses reached outside the window held."""
    from slam.keyframe_graph import EdgeKind

    g, r = _random_graph(seed)
    n = g.num_keyframes
    scale = {EdgeKind.ODOMETRY: 0.5, EdgeKind.LOOP: 3.0}
    for cap in (None, 1, 2):
        free = sorted(r.sample(range(1, n), min(n - 1, r.randint(1, 6))))
        want = set()
        for k in free:
            want |= {e for e, x in enumerate(g.edges) if x.kind is EdgeKind.ODOMETRY and x.active and k in (x.i, x.j)}
            loops = [e for e, x in enumerate(g.edges) if x.kind is EdgeKind.LOOP and x.active and k in (x.i, x.j)]
            want |= set(loops if cap is None else loops[len(loops) - cap:] if len(loops) > cap else loops)
        out = g.window_graph(scale, free, loops_per_keyframe=cap)
        ends = {g.edges[e].i for e in want} | {g.edges[e].j for e in want} | set(free)
        if not ends - set(free):  # nothing held: no window of its own
            assert out is None
            continue
        pg, used, rows = out
        assert rows.tolist() == sorted(want)
        assert used.tolist() == sorted(ends)
        assert [int(used[k]) for k in pg.fixed.tolist()] == sorted(ends - set(free))
        for row, e in enumerate(rows.tolist()):
            x = g.edges[e]
            assert (int(used[pg.ii[row]]), int(used[pg.jj[row]])) == (x.i, x.j)
            assert torch.equal(pg.measurements[row], x.T_ij)
            info = 0.5 * (x.information + x.information.T) * scale[x.kind]
            assert torch.allclose(pg.information[row], info, rtol=0, atol=1e-15)
        assert torch.equal(pg.poses, g.estimates()[used])
    with pytest.raises(ValueError, match=f"free keyframe {n}"):
        g.window_graph(scale, [n])


@pytest.mark.parametrize("seed", range(8))
def test_has_active_loop_is_any_active_loop_edge(seed):
    from slam.keyframe_graph import EdgeKind

    g, r = _random_graph(seed)
    loops = [k for k, e in enumerate(g.edges) if e.kind is EdgeKind.LOOP]
    for _ in range(3):
        assert g.has_active_loop() == any(g.edges[k].active for k in loops)
        for k in loops:  # every loop off, then one back on
            g.edges[k].active = False
        if loops:
            g.edges[r.choice(loops)].active = True
        else:
            assert not g.has_active_loop()
            break


def test_an_edge_keeps_its_measurement_without_a_copy():
    """A loop's edge holds the loop's own (float64) tensors: a long run keeps one pair per loop, not two; the
    rows the pose graph is built from are copies all the same."""
    g = KeyframeGraph()
    g.add_keyframe(se3_identity(dtype=D))
    T = se3_exp(torch.tensor([0.5, 0, 0, 0, 0, 0], dtype=D))
    info = 2.0 * torch.eye(6, dtype=D)
    g.add_odometry(0, T, info, T)
    e = g.add_loop(0, 1, T, info)
    assert g.edges[e].T_ij is T and g.edges[e].information is info and g.edges[0].T_ij is T
    pg = g.pose_graph({EdgeKind.ODOMETRY: 1.0, EdgeKind.LOOP: 1.0})
    assert torch.equal(pg.measurements[1], T) and torch.equal(pg.information[1], info)
    f = g.add_loop(0, 1, T.float(), info.float())  # another dtype: converted, so a new tensor
    assert g.edges[f].T_ij.dtype == D and g.edges[f].T_ij is not T
