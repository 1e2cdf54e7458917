"""The accelerator's numpy path (slam.graph.accel.host, also with its C kernels) against the torch reference
(slam.graph.fused and TorchProblem; the reference itself is checked against slam.lie, autograd, finite
differences and gradcheck in test_graph_fused and test_pose_graph)."""
import math

import numpy as np
import pytest
import torch

from slam.graph import OptimizerConfig, PoseGraph, compiled_kernels, optimize
from slam.graph.accel import host
from slam.graph.costs import edge_jacobians, edge_residuals, make_kernel
from slam.graph.fused import _qmul, se3_adjoint_t, se3_jacobians_t, se3_residuals, se3_retract
from slam.graph.linear import to_dense
from slam.graph.problem import TorchProblem
from slam.lie import quat_rotate, quat_to_rotmat, se3_between, se3_compose, se3_exp, se3_inv

F64 = torch.float64

needs_c = pytest.mark.skipif(not compiled_kernels(), reason="the C kernels slam.graph.accel._kernels were not built")


def _unit(q):
    return q / q.norm(dim=-1, keepdim=True)


def test_bilinear_tables_reproduce_the_torch_products():
    g = torch.Generator().manual_seed(0)
    a, b = _unit(torch.randn(50, 4, generator=g, dtype=F64)), _unit(torch.randn(50, 4, generator=g, dtype=F64))
    u, v = torch.randn(50, 3, generator=g, dtype=F64), torch.randn(50, 3, generator=g, dtype=F64)
    an, bn, un, vn = a.numpy(), b.numpy(), u.numpy(), v.numpy()
    np.testing.assert_allclose(host.qmul(an, bn), _qmul(a, b).numpy(), atol=1e-15)
    np.testing.assert_allclose(host.qmul_conj(an, bn), _qmul(a, b, conj_b=True).numpy(), atol=1e-15)
    np.testing.assert_allclose(host.rotate(an, un), quat_rotate(a, u).numpy(), atol=1e-14)
    np.testing.assert_allclose(host.rotmat(an), quat_to_rotmat(a).numpy(), atol=1e-15)
    np.testing.assert_allclose(host.cross(un, vn), torch.linalg.cross(u, v).numpy(), atol=1e-15)
    # hand-computed: 90 degrees about z takes x to y; i j = k
    q = np.array([[0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)]])
    np.testing.assert_allclose(host.rotate(q, np.array([[1.0, 0.0, 0.0]])), [[0.0, 1.0, 0.0]], atol=1e-15)
    np.testing.assert_array_equal(host.qmul(np.array([[1.0, 0, 0, 0]]), np.array([[0, 1.0, 0, 0]])), [[0, 0, 1.0, 0]])


def _edges(seed=3, N=12, E=40):
    """Random poses and measurements with an exact edge, one near pi and one in the series branches."""
    g = torch.Generator().manual_seed(seed)
    xi = torch.randn(N, 6, generator=g, dtype=F64)
    xi[:, 3:] *= 1.2
    P = se3_exp(xi)
    ii = torch.randint(0, N, (E,), generator=g)
    jj = (ii + torch.randint(1, N, (E,), generator=g)) % N
    dz = torch.randn(E, 6, generator=g, dtype=F64) * 0.3
    dz[0] = 0.0  # met exactly: r = 0
    dz[1, 3:] = torch.tensor([0.0, 0.0, math.pi - 1e-3])  # near pi
    dz[2, 3:] = 1e-7  # below both series thresholds
    dz[3, 3:] = 3e-3  # between them (log exact, Q series)
    return P, ii, jj, se3_compose(se3_between(P[ii], P[jj]), se3_exp(dz))


def test_residuals_jacobians_and_retraction_match_the_torch_kernels():
    P, ii, jj, Z = _edges()
    zinv = se3_inv(Z)
    r_t, aux = se3_residuals(P, ii, jj, zinv)
    r, theta2, c = host._residuals(P.numpy(), ii.numpy(), jj.numpy(), zinv[:, :3].numpy(), zinv[:, 3:].numpy())
    np.testing.assert_allclose(r, r_t.numpy(), atol=1e-12)
    np.testing.assert_allclose(r, edge_residuals(P, ii, jj, Z)[0].numpy(), atol=1e-12)
    np.testing.assert_allclose(theta2, aux[0][:, 0].numpy(), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(c, aux[1][:, 0].numpy(), rtol=1e-9)
    neg = (-se3_adjoint_t(zinv)).numpy()
    JT = host._jacobians_t(r, theta2, c, neg, np.zeros((len(ii), 13, 6)))
    np.testing.assert_allclose(JT, se3_jacobians_t(r_t, aux, -se3_adjoint_t(zinv)).numpy(), atol=1e-10)
    Ji, Jj = edge_jacobians(P, ii, jj, edge_residuals(P, ii, jj, Z)[1], r_t)
    np.testing.assert_allclose(JT[:, :6], Ji.mT.numpy(), atol=1e-10)
    np.testing.assert_allclose(JT[:, 6:12], Jj.mT.numpy(), atol=1e-10)
    step = torch.randn(P.shape[0], 6, generator=torch.Generator().manual_seed(4), dtype=F64)
    step[0], step[1], step[2] = 0.0, 1e-9, torch.tensor([0.1, 0, 0, 0, 0, math.pi - 1e-4])
    np.testing.assert_allclose(host.retract(P.numpy(), step.numpy()), se3_retract(P, step).numpy(), atol=1e-12)
    np.testing.assert_allclose(host.retract(P.numpy(), step.numpy()), se3_compose(P, se3_exp(step)).numpy(),
                               atol=1e-12)


def _graph(planar=False, seed=5):
    P, ii, jj, Z = _edges(seed, N=10, E=30)
    if planar:  # project onto the plane: z = roll = pitch = 0
        flat = torch.zeros_like(P)
        flat[:, :2], flat[:, 5:] = P[:, :2], _unit(P[:, 5:])
        P = flat
        Z = se3_compose(se3_between(P[ii], P[jj]), se3_exp(torch.tensor([0.05, -0.02, 0, 0, 0, 0.03], dtype=F64)))
    W = torch.randn(len(ii), 6, 6, generator=torch.Generator().manual_seed(seed), dtype=F64)
    info = W @ W.mT + torch.eye(6, dtype=F64)
    if planar:  # no coupling of (x, y, yaw) with (z, roll, pitch)
        mask = torch.zeros(6, 6, dtype=torch.bool)
        a, b = [0, 1, 5], [2, 3, 4]
        mask[np.ix_(a, b)] = mask[np.ix_(b, a)] = True
        info[:, mask] = 0.0
    return PoseGraph(P, ii, jj, Z, info)


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=needs_c)])  # numpy / C kernels
@pytest.mark.parametrize("planar", [False, True])
@pytest.mark.parametrize("dense_max", [10 ** 6, 0])  # dense and block-sparse normal equations
def test_normal_equations_and_steps_equal_the_torch_problem(planar, dense_max, compiled):
    graph = _graph(planar)
    assert graph.is_planar() == planar
    cfg = OptimizerConfig(fixed=(3,), damping="diagonal", dense_max=dense_max)
    for kernel in (None, "huber"):
        kern = make_kernel(kernel, None)
        ref = TorchProblem(graph, cfg, kern, "first", "dense")
        prob = host.host_problem(graph, cfg, kern, "first", "auto", compiled=compiled)
        assert prob.dense == (dense_max > 0) and prob.size == ref.size == 8 * (3 if planar else 6)
        cost_t, chi2_t, cache_t = ref.evaluate(ref.poses)
        cost, chi2, cache = prob.evaluate(prob.poses)
        assert cost == pytest.approx(cost_t, rel=1e-12) and chi2 == pytest.approx(chi2_t, rel=1e-12)
        H_t, g_t = ref.linearize(ref.poses, cache_t)
        H, g = prob.linearize(prob.poses, cache)
        H_dense = H.reshape(prob.size, prob.size) if prob.dense else to_dense(prob.pattern, torch.from_numpy(H)).numpy()
        np.testing.assert_allclose(H_dense, to_dense(ref.pattern, H_t).numpy(), rtol=1e-10, atol=1e-8)
        np.testing.assert_allclose(g, g_t.numpy(), rtol=1e-10, atol=1e-8)
        dx = prob.solve(H, g, 1e-3)
        np.testing.assert_allclose(dx, ref.solve(H_t, g_t, 1e-3).numpy(), rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(prob.retract(prob.poses, dx), ref.retract(ref.poses, torch.from_numpy(dx)).numpy(),
                                   atol=1e-12)


def test_backends_take_the_same_steps_on_a_real_sized_problem():
    graph = _graph()
    a = optimize(graph, kernel="cauchy", backend="numpy")
    b = optimize(graph, kernel="cauchy", backend="torch")
    assert (a.backend, b.backend, optimize(graph).backend) == ("numpy", "torch", "torch")
    assert optimize(graph, backend="auto").backend == ("c" if compiled_kernels() else "numpy")
    assert a.iterations == b.iterations > 2 and a.status == b.status
    np.testing.assert_allclose(a.cost_history, b.cost_history, rtol=1e-9)
    assert torch.allclose(a.graph.poses, b.graph.poses, atol=1e-8)
    assert torch.allclose(a.weights, b.weights, atol=1e-8)
    assert torch.equal(a.graph.poses[0], graph.poses[0])  # the free gauge moved back onto pose 0


def test_backend_setting_and_information_errors():
    graph = _graph()
    with pytest.raises(ValueError, match="backend must be"):
        optimize(graph, backend="jax")
    with pytest.raises(ValueError, match="does not support gauge 'prior'"):
        optimize(graph, backend="numpy", gauge="prior")
    r3 = PoseGraph(graph.poses, graph.ii, graph.jj, graph.measurements, graph.information, chart="r3so3")
    with pytest.raises(ValueError, match="does not support chart 'r3so3'"):
        optimize(r3, backend="numpy")
    assert optimize(r3, backend="auto").status == "converged"  # "auto" takes the torch path for it
    bad = graph.information.clone()
    bad[2, 0, 1] += 0.5  # not symmetric
    with pytest.raises(ValueError, match=r"information\[2\] .*not symmetric positive definite"):
        optimize(PoseGraph(graph.poses, graph.ii, graph.jj, graph.measurements, bad), backend="numpy")


def test_review_edge_cases_behave_alike_on_both_backends(monkeypatch):
    """Cases found in review: slightly non-unit measurement quaternions, ``fixed`` as an array, other
    dtypes, poses that require grad, non-finite inputs, bad LM settings, a degenerate Nielsen model."""
    graph = _graph(seed=7)
    unit = optimize(graph)
    # measurement quaternions within the 1e-3 the graph validates: normalised by both, the same optimum
    Z = graph.measurements.clone()
    Z[:, 3:] *= 1.0005
    off = PoseGraph(graph.poses, graph.ii, graph.jj, Z, graph.information)
    for backend in ("numpy", "torch") + (("c",) if compiled_kernels() else ()):
        res = optimize(off, backend=backend)
        assert res.chi2 == pytest.approx(unit.chi2, rel=1e-9) and res.iterations == unit.iterations
        assert torch.allclose(res.graph.poses, unit.graph.poses, atol=1e-9)
        for fixed in (np.array([3, 5]), torch.tensor([3, 5]), [3, 5]):
            fx = optimize(graph, fixed=fixed, backend=backend)
            assert float((fx.graph.poses[[3, 5]] - graph.poses[[3, 5]]).abs().max()) < 1e-15  # held
        grad = PoseGraph(graph.poses.clone().requires_grad_(True), graph.ii, graph.jj, graph.measurements,
                         graph.information)
        assert optimize(grad, backend=backend).chi2 == pytest.approx(unit.chi2, rel=1e-9)
        bf = optimize(graph.to(dtype=torch.bfloat16), backend=backend)
        assert bf.graph.poses.dtype == torch.bfloat16 and bf.status == "converged"
        nan_z = graph.measurements.clone()
        nan_z[4, 0] = float("nan")
        bad = PoseGraph(graph.poses, graph.ii, graph.jj, graph.measurements, graph.information)
        bad.measurements = nan_z  # after validation, as a caller mutating the tensors would
        with pytest.raises(ValueError, match="initial cost is nan"):
            optimize(bad, backend=backend)
        nan_info = graph.information.clone()
        nan_info[6, 2, 2] = float("nan")
        bad.measurements, bad.information = graph.measurements, nan_info
        with pytest.raises(ValueError, match=r"information\[6\]"):
            optimize(bad, backend=backend, check_information=False)
        with pytest.raises(ValueError, match="lambda_init > 0"):
            optimize(graph, backend=backend, lambda_init=0.0)
    # a model that predicts no decrease must not break the Nielsen rule (treated as a poor step)
    monkeypatch.setattr(host.HostProblem, "predicted_decrease", lambda self, dx, g, lam: 0.0)
    monkeypatch.setattr(TorchProblem, "predicted_decrease", lambda self, dx, g, lam: 0.0)
    for backend in ("numpy", "torch"):
        res = optimize(graph, lambda_update="nielsen", backend=backend)
        assert res.status == "converged" and res.chi2 == pytest.approx(unit.chi2, rel=1e-6)


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=needs_c)])
@pytest.mark.parametrize("chunk", [1, 7, 29])
@pytest.mark.parametrize("planar", [False, True])
@pytest.mark.parametrize("dense_max", [10 ** 6, 0])
def test_linearisation_in_chunks_of_edges_is_the_same(dense_max, planar, chunk, compiled, monkeypatch):
    """Large graphs are linearised in chunks of edges (bounded buffers): the normal equations of 30 edges
    in chunks equal those of one chunk, planar and 3D, dense and block-sparse, with a robust kernel and
    fixed poses, also when the buffers are reused by a second linearisation (numpy and C kernels)."""
    graph = _graph(planar=planar, seed=9)
    cfg = OptimizerConfig(fixed=(0, 3, 7), dense_max=dense_max, planar=planar)
    kern = make_kernel("cauchy", None)
    whole = host.host_problem(graph, cfg, kern, "first", "auto", compiled=compiled)
    _, _, cache = whole.evaluate(whole.poses)
    H1, g1 = (a.copy() for a in whole.linearize(whole.poses, cache))
    monkeypatch.setattr(host, "_CHUNK", chunk)
    chunked = host.host_problem(graph, cfg, kern, "first", "auto", compiled=compiled)
    assert chunked._F.shape[0] == chunk and chunked.dense == (dense_max > 0)
    _, _, cache = chunked.evaluate(chunked.poses)
    chunked.linearize(chunked.poses, cache)
    H2, g2 = chunked.linearize(chunked.poses, cache)
    np.testing.assert_allclose(H2, H1, rtol=1e-13, atol=1e-12 * np.abs(H1).max())
    np.testing.assert_allclose(g2, g1, rtol=1e-13, atol=1e-12 * np.abs(g1).max())


def test_problems_and_accelerators_satisfy_their_protocols():
    from slam.graph.accel import ACCELERATORS, Accelerator, accelerator_for
    from slam.graph.problem import PoseGraphProblem

    graph = _graph(seed=3)
    cfg = OptimizerConfig()
    assert isinstance(TorchProblem(graph, cfg, None, "free", "auto"), PoseGraphProblem)
    for name, acc in ACCELERATORS.items():
        assert isinstance(acc, Accelerator) and acc.name == name
        if acc.available():
            assert isinstance(acc.problem(graph, cfg, None, "free", "auto"), PoseGraphProblem)
        assert acc.unsupported(graph, cfg, "prior") == ["gauge 'prior'"]
    assert accelerator_for(graph, cfg, "free") is None  # the default backend is torch
    auto = accelerator_for(graph, OptimizerConfig(backend="auto"), "free")
    assert auto is ACCELERATORS["c" if compiled_kernels() else "numpy"]
    assert accelerator_for(graph, OptimizerConfig(backend="auto"), "prior") is None  # falls back to torch
