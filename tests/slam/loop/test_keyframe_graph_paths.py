"""KeyframeGraph.path_lengths_to: the distances of path_lengths (scipy's Dijkstra over the whole graph) to
chosen keyframes, by a search that stops at them; chain positions; the growing arrays behind them."""
from __future__ import annotations

import random

import numpy as np
import pytest
import torch

from slam.keyframe_graph import GrowingArray, KeyframeGraph
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
    assert g.num_weak == 1
    assert g.path_lengths(4, through_loops=False)[3] == pytest.approx(0.75)
    assert np.isinf(g.path_lengths(4, through_loops=False)[2])


def test_growing_array_keeps_its_rows():
    a = GrowingArray(np.int64, (2,))
    for k in range(100):
        a.append((k, -k))
    assert len(a) == 100 and a.view[:, 0].tolist() == list(range(100)) and a.view[57, 1] == -57
