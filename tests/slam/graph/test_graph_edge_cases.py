"""Edge cases of slam/lie.py and slam/graph (regression tests)."""
import io
import math

import pytest
import torch

from slam.graph.costs import Cauchy, GemanMcClure, Huber, Tukey, edge_jacobians, edge_residuals
from slam.graph.g2o import G2OFormatError, read_g2o
from slam.graph.optimizer import optimize
from slam.graph.pose_graph import PoseGraph
from slam.lie import se3_between, se3_compose, se3_exp, se3_identity, se3_inv, se3_log, so3_exp, so3_log

D = torch.float64


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_log_at_pi_and_zero_is_finite_with_finite_gradient(dtype):
    for q in ([1.0, 0, 0, 0], [0.0, 0, 0, 1], [0.0, 0, 0, -1]):
        q = torch.tensor([q], dtype=dtype, requires_grad=True)
        xi = se3_log(torch.cat([torch.ones(1, 3, dtype=dtype), q], 1))
        (g,) = torch.autograd.grad(xi.sum(), q)
        assert torch.isfinite(xi).all() and torch.isfinite(g).all()
    assert torch.allclose(so3_log(torch.tensor([[1.0, 0, 0, 0]], dtype=dtype)),
                          torch.tensor([[math.pi, 0, 0]], dtype=dtype))


def test_so3_log_sign_and_scale_invariant():
    q = so3_exp(torch.tensor([[0.3, -0.2, 0.5]], dtype=D))
    for other in (-q, 2.0 * q, -0.5 * q):
        assert torch.allclose(so3_log(other), so3_log(q))


@pytest.mark.parametrize("angle", [0.0, 1e-5, 1.0, 3.0, math.pi - 1e-3])
@pytest.mark.parametrize("chart", ["se3", "r3so3"])
def test_edge_jacobians_match_finite_differences_at_large_rotations(angle, chart):
    g = torch.Generator().manual_seed(3)
    P = se3_exp(torch.randn(2, 6, dtype=D, generator=g))
    axis = torch.randn(3, dtype=D, generator=g)
    err = torch.cat([torch.randn(3, dtype=D, generator=g), angle * axis / axis.norm()])
    Z = se3_compose(se3_between(P[:1], P[1:]), se3_inv(se3_exp(err[None])))
    ii, jj = torch.tensor([0]), torch.tensor([1])
    r, Dp = edge_residuals(P, ii, jj, Z, chart)
    Js = edge_jacobians(P, ii, jj, Dp, r, chart)
    eps = 1e-6
    for v, J in enumerate(Js):
        for k in range(6):
            d = torch.zeros(2, 6, dtype=D)
            d[v, k] = eps
            rp, _ = edge_residuals(se3_compose(P, se3_exp(d)), ii, jj, Z, chart)
            rm, _ = edge_residuals(se3_compose(P, se3_exp(-d)), ii, jj, Z, chart)
            assert torch.allclose((rp - rm) / (2 * eps), J[:, :, k], atol=1e-7)


@pytest.mark.parametrize("K", [Huber, Cauchy, Tukey, GemanMcClure])
def test_kernel_weight_is_derivative_of_rho_at_zero_and_width(K):
    k = K(2.0)
    s = torch.tensor([0.0, 4.0 - 1e-9, 4.0, 4.0 + 1e-9, 1e6], dtype=D, requires_grad=True)
    rho, w = k(s)
    (g,) = torch.autograd.grad(rho.sum(), s)
    assert torch.allclose(g, w, atol=1e-12)
    rho, w = rho.detach(), w.detach()
    assert float(rho[0]) == 0.0 and float(w[0]) == 1.0
    assert abs(float(rho[2] - rho[1])) < 1e-8 and abs(float(rho[3] - rho[2])) < 1e-8


def test_empty_single_pose_and_disconnected_graphs():
    I = se3_identity(dtype=D)
    with pytest.raises(ValueError, match="no edges"):
        optimize(PoseGraph.from_lists([I], []))
    with pytest.raises(ValueError, match="not a pose index"):
        PoseGraph.from_lists([I, I], [(0, 5, I)])
    step = se3_exp(torch.full((6,), 0.1, dtype=D))
    g = PoseGraph.from_lists([I] * 4, [(0, 1, step), (2, 3, step)])
    res = optimize(g, method="gn")  # an unconstrained component: a clear status, not NaN poses
    assert res.status == "solver_failed" and res.message and torch.isfinite(res.graph.poses).all()
    res = optimize(g, method="lm")
    assert res.converged and res.chi2 < 1e-12
    dup = optimize(PoseGraph.from_lists([I, I], [(0, 1, step)] * 2))
    assert dup.chi2 < 1e-12


def test_status_and_history_at_max_iterations():
    g = torch.Generator().manual_seed(0)
    P = [se3_exp(torch.randn(6, dtype=D, generator=g)) for _ in range(5)]
    step = se3_exp(torch.full((6,), 0.3, dtype=D))
    graph = PoseGraph.from_lists(P, [(i, i + 1, step) for i in range(4)] + [(0, 4, se3_identity(dtype=D))])
    res = optimize(graph, max_iterations=1)
    assert res.status == "max_iterations" and res.iterations == 1 and len(res.cost_history) == 2
    assert res.cost_history[1] < res.cost_history[0]
    # why it stopped and what to try: a better start, or more iterations once the start is one
    assert "max_iterations=1" in res.message and "initialization='chordal'" in res.message
    res = optimize(graph, max_iterations=1, initialization="chordal")
    assert res.status == "max_iterations" and "lambda_update='nielsen'" in res.message
    res = optimize(graph, max_iterations=0)
    assert res.status == "max_iterations" and res.iterations == 0 and len(res.cost_history) == 1


_V = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 7 0 0 0 0 0 0 1\n"
_E = "EDGE_SE3:QUAT 7 0 1 0 0 0 0 0 1 "
_I = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"


@pytest.mark.parametrize("info,match", [
    (_I[:-2], "expects 30 fields"),
    ("nan" + _I[1:], "non-finite"),
    ("-1" + _I[1:], "not positive definite"),
])
def test_g2o_malformed_lines_name_the_line(info, match):
    with pytest.raises(G2OFormatError, match=match) as e:
        read_g2o(io.StringIO(_V + _E + info + "\n"), strict=True)
    assert e.value.line == 3


def test_g2o_noncontiguous_ids():
    g = read_g2o(io.StringIO(_V + _E + _I + "\n"))
    assert g.vertex_ids.tolist() == [0, 7] and g.ii.tolist() == [1] and g.jj.tolist() == [0]


def _random_graph(seed=7, N=10, E=30):
    """Random poses, measurements near the relative poses and random SPD information matrices."""
    g = torch.Generator().manual_seed(seed)
    P = se3_exp(torch.randn(N, 6, generator=g, dtype=D) * 1.2)
    ii = torch.randint(0, N, (E,), generator=g)
    jj = (ii + torch.randint(1, N, (E,), generator=g)) % N
    Z = se3_compose(se3_between(P[ii], P[jj]), se3_exp(torch.randn(E, 6, generator=g, dtype=D) * 0.3))
    W = torch.randn(E, 6, 6, generator=g, dtype=D)
    return PoseGraph(P, ii, jj, Z, W @ W.mT + torch.eye(6, dtype=D))


def test_odd_inputs_are_normalised_or_refused(monkeypatch):
    """Slightly non-unit measurement quaternions, ``fixed`` as an array, other dtypes, poses that require
    grad, non-finite inputs, bad LM settings and a degenerate Nielsen model."""
    import numpy as np

    from slam.graph.problem import TorchProblem

    graph = _random_graph()
    unit = optimize(graph)
    # measurement quaternions within the 1e-3 the graph validates are normalised: the same optimum
    Z = graph.measurements.clone()
    Z[:, 3:] *= 1.0005
    res = optimize(PoseGraph(graph.poses, graph.ii, graph.jj, Z, graph.information))
    assert res.chi2 == pytest.approx(unit.chi2, rel=1e-9) and res.iterations == unit.iterations
    assert torch.allclose(res.graph.poses, unit.graph.poses, atol=1e-9)
    for fixed in (np.array([3, 5]), torch.tensor([3, 5]), [3, 5]):
        fx = optimize(graph, fixed=fixed)
        assert float((fx.graph.poses[[3, 5]] - graph.poses[[3, 5]]).abs().max()) < 1e-15  # held
    grad = PoseGraph(graph.poses.clone().requires_grad_(True), graph.ii, graph.jj, graph.measurements,
                     graph.information)
    assert optimize(grad).chi2 == pytest.approx(unit.chi2, rel=1e-9)
    bf = optimize(graph.to(dtype=torch.bfloat16))
    assert bf.graph.poses.dtype == torch.bfloat16 and bf.status == "converged"
    nan_z = graph.measurements.clone()
    nan_z[4, 0] = float("nan")
    bad = PoseGraph(graph.poses, graph.ii, graph.jj, graph.measurements, graph.information)
    bad.measurements = nan_z  # after validation, as a caller mutating the tensors would
    with pytest.raises(ValueError, match="initial cost is nan"):
        optimize(bad)
    nan_info = graph.information.clone()
    nan_info[6, 2, 2] = float("nan")
    bad.measurements, bad.information = graph.measurements, nan_info
    with pytest.raises(ValueError, match=r"information\[6\]"):
        optimize(bad, check_information=False)
    with pytest.raises(ValueError, match="lambda_init > 0"):
        optimize(graph, lambda_init=0.0)
    # a model that predicts no decrease must not break the Nielsen rule (treated as a poor step)
    monkeypatch.setattr(TorchProblem, "predicted_decrease", lambda self, dx, g, lam: 0.0)
    res = optimize(graph, lambda_update="nielsen")
    assert res.status == "converged" and res.chi2 == pytest.approx(unit.chi2, rel=1e-6)
