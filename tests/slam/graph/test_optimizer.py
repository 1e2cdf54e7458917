"""Gauss-Newton / Levenberg-Marquardt on pose graphs: exact solutions, loop closing, solvers, gauge,
robust kernels, the planar reduction, errors, and agreement with GTSAM on a shared benchmark file."""
import math

import pytest
import torch

from slam.graph import (
    Cauchy,
    OptimizerConfig,
    PoseGraph,
    Status,
    edge_chi2,
    edge_residuals,
    graph_chi2,
    optimize,
    read_g2o,
)
from slam.lie import se3_between, se3_compose, se3_exp, se3_log

F64 = torch.float64


def _truth(n=24, radius=4.0, planar=False):
    """Poses on a circle (camera looking along the tangent), with a 3D wiggle unless planar."""
    k = torch.arange(n, dtype=F64)
    a = 2 * math.pi * k / n
    xi = torch.zeros(n, 6, dtype=F64)
    xi[:, 5] = a
    P = se3_exp(xi)
    P[:, 0], P[:, 1] = radius * torch.cos(a), radius * torch.sin(a)
    if not planar:
        P[:, 2] = 0.5 * torch.sin(3 * a)
        P = se3_compose(P, se3_exp(torch.stack([0 * a, 0 * a, 0 * a, 0.2 * torch.sin(2 * a),
                                                0.1 * torch.cos(a), 0 * a], -1)))
    return P


def _loop_graph(n=24, sigma=0.0, planar=False, seed=0, extra=()):
    """Odometry chain + one loop closure (n-1 -> 0); initial guess = composed odometry."""
    g = torch.Generator().manual_seed(seed)
    T = _truth(n, planar=planar)
    ii = torch.cat([torch.arange(n - 1), torch.tensor([n - 1])])
    jj = torch.cat([torch.arange(1, n), torch.tensor([0])])
    for i, j in extra:
        ii, jj = torch.cat([ii, torch.tensor([i])]), torch.cat([jj, torch.tensor([j])])
    E = ii.shape[0]
    noise = torch.randn(E, 6, generator=g, dtype=F64) * sigma
    noise[:, 3:] *= 0.5
    if planar:
        noise[:, [2, 3, 4]] = 0.0
    Z = se3_compose(se3_between(T[ii], T[jj]), se3_exp(noise))
    info = torch.diag(torch.tensor([1.0, 1.0, 1.0, 4.0, 4.0, 4.0], dtype=F64)) / max(sigma, 1e-3) ** 2
    init = [T[0]]
    for k in range(n - 1):
        init.append(se3_compose(init[-1], Z[k]))
    return PoseGraph(torch.stack(init), ii, jj, Z, info.expand(E, 6, 6).clone()), T


def _stationarity(graph):
    """Gradient of chi2 w.r.t. right perturbations of every pose except the first, by autograd."""
    d = torch.zeros(graph.num_poses, 6, dtype=F64, requires_grad=True)
    P = se3_compose(graph.poses, se3_exp(d))
    r, _ = edge_residuals(P, graph.ii, graph.jj, graph.measurements)
    (grad,) = torch.autograd.grad(edge_chi2(r, graph.information).sum(), d)
    return grad[1:]


@pytest.mark.parametrize("method", ["lm", "gn"])
def test_exact_solution_is_recovered(method):
    g, T = _loop_graph(n=12, sigma=0.0, extra=[(2, 7), (4, 10)])
    gen = torch.Generator().manual_seed(1)
    start = se3_compose(T, se3_exp(torch.randn(12, 6, generator=gen, dtype=F64) * 0.2))
    start[0] = T[0]
    res = optimize(g.with_poses(start), method=method)
    assert res.status == Status.CONVERGED and res.status == "converged"
    assert res.chi2 < 1e-12 < res.initial_chi2
    assert float((res.graph.poses[:, :3] - T[:, :3]).abs().max()) < 1e-7
    assert float(se3_log(se3_between(res.graph.poses, T)).abs().max()) < 1e-7


def test_noisy_loop_is_closed_at_a_stationary_point():
    g, _ = _loop_graph(n=30, sigma=0.05, seed=2)
    loop = g.num_edges - 1
    r0, _ = edge_residuals(g.poses, g.ii, g.jj, g.measurements)
    res = optimize(g, "lm")
    r1, _ = edge_residuals(res.graph.poses, g.ii, g.jj, g.measurements)
    assert res.status == "converged" and res.iterations == len(res.cost_history) - 1
    assert float(r0[loop].norm()) > 50 * float(r1[loop].norm())  # the drift is spread over the loop
    assert res.chi2 < 0.05 * res.initial_chi2 and res.chi2 < 27.9  # chi2 with 6 dof of redundancy: p > 1e-4
    assert res.initial_chi2 == pytest.approx(graph_chi2(g))
    assert res.chi2 == pytest.approx(graph_chi2(res.graph))
    # first-order optimality, checked by autograd independently of the analytic Jacobians
    assert float(_stationarity(res.graph).norm()) < 1e-5 * float(_stationarity(g).norm())
    hist = torch.tensor(res.cost_history)
    assert bool((hist[1:] <= hist[:-1]).all())  # LM only accepts decreasing steps
    assert res.error == pytest.approx(res.chi2 / 2) and set(res.timings) >= {"linearize", "solve", "total"}


@pytest.mark.parametrize("solver", ["auto", "dense"])
def test_linear_solvers_agree(solver):
    g, _ = _loop_graph(n=20, sigma=0.05, seed=3, extra=[(3, 12)])
    ref = optimize(g, solver="sparse")
    res = optimize(g, solver=solver)
    assert res.chi2 == pytest.approx(ref.chi2, rel=1e-8)
    assert torch.allclose(res.graph.poses, ref.graph.poses, atol=1e-6)


def test_a_user_solver_object_plugs_in():
    """A factorisation of the user's own (scipy's sparse LU here) plugs in as a LinearSolver object and
    reaches the built-in sparse Cholesky's optimum; the block pattern it is handed is the whole system."""
    scipy_sparse = pytest.importorskip("scipy.sparse")
    from scipy.sparse.linalg import spsolve

    from slam.graph import LinearSolver
    from slam.graph.linear import to_dense

    class ScipySolver(LinearSolver):
        calls = 0

        def solve(self, pattern, values, b):
            ScipySolver.calls += 1
            A = scipy_sparse.csc_matrix(to_dense(pattern, values).numpy())
            return torch.from_numpy(spsolve(A, b.numpy())).to(b.dtype)

    g, _ = _loop_graph(n=20, sigma=0.05, seed=3, extra=[(3, 12)])
    ref = optimize(g, solver="sparse")
    res = optimize(g, solver=ScipySolver())
    assert ScipySolver.calls >= res.iterations > 0
    assert res.chi2 == pytest.approx(ref.chi2, rel=1e-8)
    assert torch.allclose(res.graph.poses, ref.graph.poses, atol=1e-6)
    with pytest.raises(ValueError, match="LinearSolver"):
        optimize(g, solver="cholmod")


def test_nielsen_lambda_update_reaches_the_same_optimum():
    g, _ = _loop_graph(n=20, sigma=0.05, seed=9, extra=[(2, 14), (6, 17)])
    ref = optimize(g)
    for damping in ("identity", "diagonal"):
        res = optimize(g, lambda_update="nielsen", damping=damping)
        assert res.status == "converged" and res.chi2 == pytest.approx(ref.chi2, rel=1e-7)
        assert torch.allclose(res.graph.poses, ref.graph.poses, atol=1e-5)
        hist = torch.tensor(res.cost_history, dtype=F64)
        assert bool((hist[1:] < hist[:-1]).all())
    # near the optimum the damped quadratic model predicts the decrease (gain ratio ~1): lambda shrinks 3x
    res = optimize(g, lambda_update="nielsen", max_iterations=3)
    assert res.lambda_history[1] == pytest.approx(res.lambda_history[0] / 3, rel=0.05)
    with pytest.raises(ValueError, match="lambda_update must be"):
        optimize(g, lambda_update="marquardt")


def test_gauge_prior_and_fixed_poses():
    g, _ = _loop_graph(n=16, sigma=0.05, seed=4)
    first = optimize(g, gauge="first")
    prior = optimize(g, gauge="prior")
    free = optimize(g, gauge="free")  # the default: LM damping, then moved back onto pose 0
    assert free.chi2 == pytest.approx(first.chi2, rel=1e-6)
    assert torch.allclose(free.graph.poses[0], g.poses[0], atol=1e-12)
    assert torch.allclose(free.graph.poses, first.graph.poses, atol=1e-5)
    assert prior.chi2 == pytest.approx(first.chi2, rel=1e-6)
    assert float((prior.graph.poses[0] - g.poses[0]).abs().max()) < 1e-6
    assert torch.allclose(prior.graph.poses, first.graph.poses, atol=1e-5)
    fixed = optimize(g, fixed=(5,), gauge="first")
    assert torch.allclose(fixed.graph.poses[[0, 5]], g.poses[[0, 5]], atol=1e-15, rtol=0)
    anchored = optimize(g, fixed=(5,))  # with the free gauge, the fixed pose anchors the result
    assert torch.allclose(anchored.graph.poses[5], g.poses[5], atol=1e-15, rtol=0)
    assert anchored.chi2 == pytest.approx(first.chi2, rel=1e-6)
    assert fixed.chi2 >= first.chi2
    with pytest.raises(ValueError, match="out of range"):
        optimize(g, fixed=(99,))


def test_robust_kernel_rejects_a_false_loop_closure():
    g, _ = _loop_graph(n=16, sigma=0.01, seed=5, extra=[(3, 11)])
    # replace the (5, 20) loop closure by a wrong one: 3 m and 90 degrees off
    off = se3_exp(torch.tensor([3.0, 0, 0, 0, 0, 1.57], dtype=F64))
    g.measurements[-1] = se3_compose(g.measurements[-1], off)
    keep = torch.arange(g.num_edges - 1)
    clean = optimize(PoseGraph(g.poses, g.ii[keep], g.jj[keep], g.measurements[keep], g.information[keep]))
    plain = optimize(g)
    robust = optimize(g, kernel=Cauchy(1.0))
    by_name = optimize(g, kernel="cauchy")

    def err(res):  # distance to the solution without the false edge
        return float((res.graph.poses[:, :3] - clean.graph.poses[:, :3]).norm(dim=-1).max())

    assert err(plain) > 0.5 and err(robust) < 1e-2 and err(by_name) < 1e-2
    assert float(robust.weights[-1]) < 1e-3 and float(robust.weights[:-1].min()) > 0.5
    assert robust.robust_cost is not None and robust.robust_cost < robust.chi2 and plain.robust_cost is None


def test_planar_graph_uses_the_reduced_system_and_stays_planar():
    g, _ = _loop_graph(n=20, sigma=0.05, planar=True, seed=6, extra=[(4, 15)])
    assert g.is_planar()
    reduced = optimize(g)
    full = optimize(g, planar=False)
    assert reduced.chi2 == pytest.approx(full.chi2, rel=1e-9)
    assert torch.allclose(reduced.graph.poses, full.graph.poses, atol=1e-8)
    assert reduced.graph.is_planar(tol=1e-12)


@pytest.mark.parametrize("solver", ["sparse", "dense"])
def test_gn_on_an_unconstrained_pose_fails_cleanly_and_lm_still_works(solver):
    g, _ = _loop_graph(n=10, sigma=0.05, seed=7)
    P = torch.cat([g.poses, se3_exp(torch.ones(1, 6, dtype=F64))])  # pose 10 is in no edge
    h = PoseGraph(P, g.ii, g.jj, g.measurements, g.information)
    gn = optimize(h, "gn", solver=solver)
    assert gn.status == "solver_failed" and "positive definite" in gn.message
    assert torch.allclose(gn.graph.poses, h.poses, atol=1e-15, rtol=0)
    for gauge in ("first", "free"):  # the damping makes the unconstrained pose harmless
        lm = optimize(h, "lm", gauge=gauge, solver=solver)
        ref = optimize(g, "lm", gauge=gauge, solver=solver)
        assert lm.status == "converged" and lm.chi2 == pytest.approx(ref.chi2, rel=1e-9)
        if gauge == "first":  # no gradient, no step: it stays where it is
            assert torch.allclose(lm.graph.poses[10], h.poses[10], atol=1e-15, rtol=0)


def test_status_results_and_errors():
    g, _ = _loop_graph(n=10, sigma=0.05, seed=8)
    one = optimize(g, max_iterations=1)
    assert one.status == Status.MAX_ITERATIONS and one.iterations == 1
    half = optimize(g.to(dtype=torch.float32))
    assert half.graph.poses.dtype == torch.float32 and half.status == "converged"
    assert optimize(g, "lm", kernel="huber", config=OptimizerConfig(max_iterations=50)).status == "converged"
    with pytest.raises(ValueError, match="no edges"):
        optimize(PoseGraph(g.poses, g.ii[:0], g.jj[:0], g.measurements[:0], g.information[:0]))
    bad = g.information.clone()
    bad[3] = -bad[3]
    with pytest.raises(ValueError, match=r"information\[3\] .*not symmetric positive definite"):
        optimize(PoseGraph(g.poses, g.ii, g.jj, g.measurements, bad))
    with pytest.raises(ValueError, match="method must be"):
        optimize(g, method="dogleg")
    with pytest.raises(ValueError, match="gauge must be"):
        optimize(g, gauge="mean")
    with pytest.raises(TypeError):
        optimize(g, not_a_setting=1)


@pytest.mark.parametrize("name", ["tinyGrid3D", "smallGrid3D"])
def test_matches_gtsam_levenberg_marquardt(posegraph_dir, name):
    gtsam = pytest.importorskip("gtsam")
    path = str(posegraph_dir / f"{name}.g2o")
    graph, initial = gtsam.readG2o(path, True)
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams()).optimize()
    gtsam_error = graph.error(result)
    ours = optimize(read_g2o(path), "lm")
    assert ours.status == "converged"
    assert ours.initial_chi2 / 2 == pytest.approx(graph.error(initial), rel=1e-9)
    assert ours.chi2 / 2 <= 1.0001 * gtsam_error
    assert ours.chi2 / 2 == pytest.approx(gtsam_error, rel=1e-6)


def test_torch_fallback_of_the_fused_kernels_gives_the_same_result(monkeypatch):
    """Off the CPU the fused kernels use torch.matmul / copy_ instead of numpy: same optimum (this runs
    the torch branch on the CPU)."""
    from slam.graph import fused

    graph, _ = _loop_graph(20, sigma=0.05, seed=2, extra=[(3, 12), (5, 17)])
    ref = optimize(graph, kernel="huber")
    monkeypatch.setattr(fused, "_numpy_ok", lambda *ts: False)
    res = optimize(graph, kernel="huber")
    assert res.iterations == ref.iterations and res.chi2 == pytest.approx(ref.chi2, rel=1e-10)
    assert torch.allclose(res.graph.poses, ref.graph.poses, atol=1e-9)


def test_a_problem_reuses_the_buffers_of_the_previous_one_with_the_same_results():
    """The per-edge buffers an optimisation hands back serve the next problem (any size, chart or planarity):
    its result equals the one computed with fresh buffers, bit for bit."""
    import dataclasses

    import slam.graph.problem as problem

    big, _ = _loop_graph(n=30, sigma=0.05, seed=1, extra=[(2, 20), (5, 25)])
    big = dataclasses.replace(big, chart="r3so3")  # writes every entry of the Jacobian buffer
    small, _ = _loop_graph(n=12, sigma=0.05, planar=True, seed=2)
    problem._WORKSPACES.clear()
    fresh = [optimize(g, solver="sparse") for g in (small, big)]
    problem._WORKSPACES.clear()
    optimize(big, solver="sparse")
    (ws,) = problem._WORKSPACES  # handed back when the optimisation ended
    prob = problem.TorchProblem(small, OptimizerConfig(), None, "free", "sparse")
    assert prob.ws is ws and not problem._WORKSPACES  # taken by one problem at a time
    prob.release()
    again = [optimize(g, solver="sparse") for g in (small, big)]
    for a, b in zip(fresh, again):
        assert torch.equal(a.graph.poses, b.graph.poses) and a.chi2 == b.chi2
