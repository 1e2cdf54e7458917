"""slam.graph.initialization: spanning-tree and chordal initial guesses, and optimize(initialization=...)."""
from __future__ import annotations

import io
from collections import deque

import numpy as np
import pytest
import torch

from benchmarks.simulate import compose_chain
from slam.graph import PoseGraph, graph_chi2, optimize, read_g2o, write_g2o
from slam.graph.initialization import (
    AUTO_CHI2_PER_EDGE,
    INITIALIZATIONS,
    chordal_poses,
    initial_poses,
    initialize,
    spanning_tree,
    spanning_tree_poses,
)
from slam.lie import quat_to_rotmat, se3_between, se3_compose, se3_exp, se3_identity, se3_inv

F64 = torch.float64


def _random_graph(n=30, extra=25, seed=0, noise=0.0, info=None):
    """A connected graph on random true poses: a chain plus random chords; measurements with noise."""
    g = torch.Generator().manual_seed(seed)
    X = se3_exp(torch.randn(n, 6, generator=g, dtype=F64))
    ii = torch.cat([torch.arange(n - 1), torch.randint(0, n, (extra,), generator=g)])
    jj = torch.cat([torch.arange(1, n), torch.randint(0, n, (extra,), generator=g)])
    keep = ii != jj
    ii, jj = ii[keep], jj[keep]
    Z = se3_between(X[ii], X[jj])
    if noise:
        Z = se3_compose(Z, se3_exp(noise * torch.randn(ii.numel(), 6, generator=g, dtype=F64)))
    if info is None:
        A = torch.randn(ii.numel(), 6, 6, generator=g, dtype=F64)
        info = A @ A.mT + 6 * torch.eye(6, dtype=F64)
    start = se3_identity(n, dtype=F64)
    start[0] = X[0]
    return PoseGraph(start, ii, jj, Z, info), X


def test_consistent_measurements_are_recovered_exactly():
    g, X = _random_graph()
    for method in ("spanning_tree", "chordal"):
        P = initial_poses(g, method)
        assert torch.allclose(P[:, :3], X[:, :3], atol=1e-9), method
        assert torch.allclose(quat_to_rotmat(P[:, 3:]), quat_to_rotmat(X[:, 3:]), atol=1e-9), method
        assert torch.equal(P[0], X[0])  # the anchor keeps its value
        assert graph_chi2(g.with_poses(P)) < 1e-15
    assert initial_poses(g, "none") is g.poses and initialize(g, "none") is g
    assert set(INITIALIZATIONS) == {"none", "spanning_tree", "chordal", "auto"}


def _dense_chordal(g: PoseGraph):
    """Independent reference: the same two least-squares problems, one edge at a time, dense lstsq."""
    n = g.num_poses
    Z = quat_to_rotmat(g.measurements[:, 3:]).numpy()
    info = g.information.numpy()
    R0 = quat_to_rotmat(g.poses[0, 3:]).numpy()
    rows, rhs = [], []
    for e, (i, j) in enumerate(zip(g.ii.tolist(), g.jj.tolist())):
        kappa = 1.5 / np.trace(np.linalg.inv(info[e, 3:, 3:]))
        for c in range(3):  # row c of R_i Z - R_j, i.e. Z^T r_i^c - r_j^c with r^c the c-th row as a column
            for r in range(3):
                a = np.zeros(9 * n)
                a[9 * i + 3 * c: 9 * i + 3 * c + 3] = np.sqrt(kappa) * Z[e][:, r]
                a[9 * j + 3 * c + r] -= np.sqrt(kappa)
                rows.append(a)
                rhs.append(0.0)
    A, b = np.array(rows), np.array(rhs)
    x0 = R0.reshape(-1)  # the anchor's 9 unknowns are known
    b = b - A[:, :9] @ x0
    x = np.linalg.lstsq(A[:, 9:], b, rcond=None)[0]
    M = np.concatenate([x0, x]).reshape(n, 3, 3)
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    R = U @ (np.eye(3)[None] * np.stack([np.ones(n), np.ones(n), d], -1)[:, None, :]) @ Vt
    R[0] = R0
    rows, rhs = [], []
    for e, (i, j) in enumerate(zip(g.ii.tolist(), g.jj.tolist())):
        L = np.linalg.cholesky(info[e, :3, :3])
        W = L.T @ R[i].T
        a = np.zeros((3, 3 * n))
        a[:, 3 * i: 3 * i + 3] -= W
        a[:, 3 * j: 3 * j + 3] += W
        rows.append(a)
        rhs.append(L.T @ g.measurements[e, :3].numpy())
    A, b = np.concatenate(rows), np.concatenate(rhs)
    t0 = g.poses[0, :3].numpy()
    t = np.linalg.lstsq(A[:, 3:], b - A[:, :3] @ t0, rcond=None)[0]
    return R, np.concatenate([t0, t]).reshape(n, 3)


def test_chordal_equals_a_dense_reference_on_noisy_graphs():
    g, _ = _random_graph(n=12, extra=10, seed=3, noise=0.3)
    R_ref, t_ref = _dense_chordal(g)
    P = chordal_poses(g)
    assert np.abs(quat_to_rotmat(P[:, 3:]).numpy() - R_ref).max() < 1e-10
    assert np.abs(P[:, :3].numpy() - t_ref).max() < 1e-9


def test_chordal_rotations_beat_gtsams_on_the_chordal_cost(posegraph_dir):
    """GTSAM anchors its relaxation softly (a unit-precision prior), which shrinks the relaxed matrices
    before rounding; the hard anchor here gives a chordal cost no higher and rotations within 1e-2."""
    gtsam = pytest.importorskip("gtsam")
    path = posegraph_dir / "tinyGrid3D.g2o"
    G, V = gtsam.readG2o(str(path), True)
    G.add(gtsam.PriorFactorPose3(0, V.atPose3(0), gtsam.noiseModel.Isotropic.Sigma(6, 1e-8)))
    vv = gtsam.InitializePose3.computeOrientationsChordal(gtsam.InitializePose3.buildPose3graph(G))
    g = read_g2o(path)
    ours = quat_to_rotmat(chordal_poses(g)[:, 3:]).numpy()
    theirs = np.stack([vv.atRot3(k).matrix() for k in range(g.num_poses)])
    Z = quat_to_rotmat(g.measurements[:, 3:]).numpy()
    ii, jj = g.ii.numpy(), g.jj.numpy()
    cost = [float(((R[ii] @ Z - R[jj]) ** 2).sum()) for R in (ours, theirs)]
    assert cost[0] <= cost[1] and np.abs(ours - theirs).max() < 1e-2


def test_spanning_tree_is_breadth_first_and_takes_the_best_parallel_edge():
    g, _ = _random_graph(n=40, extra=40, seed=5)
    # a parallel edge 0 - 1 with far more information than the chain's, reversed
    g.add_edge(1, 0, se3_between(g.poses[1], g.poses[0]), 1e6 * torch.eye(6, dtype=F64))
    tree = spanning_tree(g)
    # depth of every pose = its BFS distance from pose 0 (computed independently)
    adj = {v: set() for v in range(g.num_poses)}
    for i, j in zip(g.ii.tolist(), g.jj.tolist()):
        adj[i].add(j)
        adj[j].add(i)
    dist, queue = {0: 0}, deque([0])
    while queue:
        v = queue.popleft()
        for w in adj[v]:
            if w not in dist:
                dist[w] = dist[v] + 1
                queue.append(w)

    def depth(v):
        return 0 if tree.parent[v] < 0 else 1 + depth(int(tree.parent[v]))

    assert tree.roots.tolist() == [0] and tree.parent[0] == -1
    assert all(depth(v) == dist[v] for v in range(g.num_poses))
    for v in range(1, g.num_poses):  # the tree edge joins v and its parent
        e = int(tree.edge[v])
        assert {int(g.ii[e]), int(g.jj[e])} == {v, int(tree.parent[v])}
    assert int(tree.edge[1]) == g.num_edges - 1  # the most informative of the two 0 - 1 edges


def test_tree_composition_equals_the_sequential_chain():
    gen = torch.Generator().manual_seed(1)
    steps = se3_exp(0.5 * torch.randn(300, 6, generator=gen, dtype=F64))
    first = se3_exp(torch.randn(6, generator=gen, dtype=F64))
    ref = compose_chain(first, steps)
    # a chain given backwards (edges k+1 -> k) so that every tree step inverts its measurement
    start = se3_identity(301, dtype=F64)
    start[0] = first
    g = PoseGraph(start, torch.arange(1, 301), torch.arange(300), se3_inv(steps),
                  torch.eye(6, dtype=F64).expand(300, 6, 6))
    P = spanning_tree_poses(g)
    assert torch.allclose(P[:, :3], ref[:, :3], atol=1e-9)
    assert torch.allclose(quat_to_rotmat(P[:, 3:]), quat_to_rotmat(ref[:, 3:]), atol=1e-10)


def test_components_fixed_poses_and_planar_graphs(posegraph_dir):
    g, X = _random_graph(n=20, extra=10, seed=2)
    # a second component (poses 20, 21) and an isolated pose 22
    P = torch.cat([g.poses, se3_exp(torch.tensor([[5.0, 0, 0, 0, 0, 1], [1.0, 2, 3, 0, 0, 0], [9.0, 9, 9, 0, 1, 0]],
                                                 dtype=F64))])
    step = se3_exp(torch.tensor([1.0, 0, 0, 0, 0, 0], dtype=F64))
    h = PoseGraph(P, torch.cat([g.ii, torch.tensor([20])]), torch.cat([g.jj, torch.tensor([21])]),
                  torch.cat([g.measurements, step[None]]), torch.cat([g.information, torch.eye(6, dtype=F64)[None]]),
                  fixed=[7])
    for method in ("spanning_tree", "chordal"):
        out = initial_poses(h, method)
        assert torch.equal(out[7], P[7]) and torch.equal(out[20], P[20]) and torch.equal(out[22], P[22])
        assert torch.allclose(out[21], se3_compose(P[20], step), atol=1e-12)
        # the main component hangs from its fixed pose 7, not from pose 0
        assert torch.allclose(se3_between(out[7], out[:20]), se3_between(X[7], X[:20]), atol=1e-9)
    # more anchors given by the caller: chordal respects them all
    out = chordal_poses(h, fixed=[0, 3])
    assert torch.equal(out[0], P[0]) and torch.equal(out[3], P[3])
    with pytest.raises(ValueError, match="fixed pose index 99"):
        chordal_poses(h, fixed=[99])
    m = read_g2o(posegraph_dir / "input_M3500_g2o.g2o")
    for method in ("spanning_tree", "chordal"):
        assert m.with_poses(initial_poses(m, method)).is_planar(tol=0.0)


def test_optimize_keyword(posegraph_dir):
    g = read_g2o(posegraph_dir / "smallGrid3D.g2o")
    ref = optimize(g)
    for method in ("spanning_tree", "chordal"):
        res = optimize(g, initialization=method)
        assert res.chi2 == pytest.approx(ref.chi2, rel=1e-6) and res.converged
        assert res.initial_chi2 < 0.6 * ref.initial_chi2  # it started from the better guess
        assert torch.equal(res.graph.poses[0], g.poses[0])
    with pytest.raises(ValueError, match="initialization must be one of"):
        optimize(g, initialization="odometry")


def test_auto_keeps_poses_that_fit_the_edges_and_composes_the_tree_otherwise():
    """``"auto"``: the graph's poses when their chi2 per edge is at most AUTO_CHI2_PER_EDGE, else the
    spanning tree's; optimize's own test (on its first evaluation) picks the same start."""
    g, X = _random_graph(noise=0.01)
    near = g.with_poses(se3_compose(X, se3_exp(0.01 * torch.randn(X.shape[0], 6, dtype=F64,
                                                                  generator=torch.Generator().manual_seed(1)))))
    near.poses[0] = X[0]
    far = g  # every pose but the anchor at the identity
    assert graph_chi2(near) <= AUTO_CHI2_PER_EDGE * near.num_edges < graph_chi2(far)
    assert initial_poses(near, "auto") is near.poses
    assert torch.equal(initial_poses(far, "auto"), spanning_tree_poses(far))
    for graph, same in ((near, "none"), (far, "spanning_tree")):
        res, ref = optimize(graph, initialization="auto"), optimize(graph, initialization=same)
        assert res.initial_chi2 == ref.initial_chi2 and res.iterations == ref.iterations
        assert torch.equal(res.graph.poses, ref.graph.poses)


def _sphere_big_noise(posegraph_dir, n=500, sigma_t=0.3, sigma_r=0.2, seed=0):
    """The first ``n`` poses of sphere2500 (as the file gives them) re-measured with large noise, started
    from the composed odometry: the construction of GTSAM's sphere_bignoise (held out here)."""
    g = read_g2o(posegraph_dir / "sphere2500.g2o")
    X = g.poses
    keep = (g.ii < n) & (g.jj < n)
    ii, jj = g.ii[keep], g.jj[keep]
    gen = torch.Generator().manual_seed(seed)
    sig = torch.tensor([sigma_t] * 3 + [sigma_r] * 3, dtype=F64)
    Z = se3_compose(se3_between(X[ii], X[jj]), se3_exp(sig * torch.randn(ii.numel(), 6, generator=gen, dtype=F64)))
    odo = jj == ii + 1
    P = compose_chain(X[0], Z[odo][torch.argsort(ii[odo])])
    return PoseGraph(P, ii, jj, Z, torch.diag(sig ** -2).expand(ii.numel(), 6, 6).clone())


@pytest.mark.slow
def test_chordal_finds_the_better_optimum_of_a_sphere_with_large_noise(posegraph_dir, tmp_path):
    """From the odometry LM stops in a local minimum 3x above; from the chordal guess it reaches the one
    GTSAM's InitializePose3 + LM reaches (no higher than GTSAM's, to its stopping tolerance 1e-5)."""
    g = _sphere_big_noise(posegraph_dir)
    from_file = optimize(g)
    chordal = optimize(g, initialization="chordal")
    assert chordal.converged and chordal.chi2 < 0.5 * from_file.chi2
    gtsam = pytest.importorskip("gtsam")
    path = tmp_path / "sphere_big.g2o"
    write_g2o(path, g)
    G, V = gtsam.readG2o(str(path), True)
    G2 = gtsam.NonlinearFactorGraph(G)
    G2.add(gtsam.PriorFactorPose3(0, V.atPose3(0), gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)))
    res = gtsam.LevenbergMarquardtOptimizer(G, gtsam.InitializePose3.initialize(G2),
                                            gtsam.LevenbergMarquardtParams()).optimize()
    assert chordal.chi2 <= 2 * G.error(res) * (1 + 1e-5)


def test_read_back_initialised_graph_round_trips(tmp_path):
    g, _ = _random_graph(n=8, extra=4, seed=9, noise=0.05)
    h = initialize(g, "chordal")
    buf = io.StringIO()
    write_g2o(buf, h)
    back = read_g2o(io.StringIO(buf.getvalue()))
    assert torch.allclose(back.poses, h.poses, atol=1e-15)
