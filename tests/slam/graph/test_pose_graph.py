"""PoseGraph construction/validation, residuals, analytic Jacobians and robust kernels."""
import math

import pytest
import torch

from slam.graph import (
    Cauchy,
    GemanMcClure,
    Huber,
    PoseGraph,
    Tukey,
    edge_jacobians,
    edge_residuals,
    graph_chi2,
    make_kernel,
)
from slam.graph.linear import assemble_blocks, build_pattern, to_dense
from slam.lie import se3_between, se3_compose, se3_exp, se3_identity, se3_log

F64 = torch.float64


def _random_graph(n=6, seed=0, rot=1.0):
    g = torch.Generator().manual_seed(seed)
    poses = se3_exp(torch.randn(n, 6, generator=g, dtype=F64) * rot)
    ii = torch.tensor([0, 1, 2, 3, 4, 0, 1], dtype=torch.long)[: n + 1]
    jj = torch.tensor([1, 2, 3, 4, 5, 3, 5], dtype=torch.long)[: n + 1]
    noise = se3_exp(torch.randn(ii.shape[0], 6, generator=g, dtype=F64) * 0.3)
    meas = se3_compose(se3_between(poses[ii], poses[jj]), noise)
    A = torch.randn(ii.shape[0], 6, 6, generator=g, dtype=F64)
    info = A @ A.mT + 0.5 * torch.eye(6, dtype=F64)
    return PoseGraph(poses, ii, jj, meas, info)


def test_construction_and_helpers():
    g = _random_graph()
    assert g.poses.shape == (6, 7) and g.ii.dtype == torch.long and g.information.shape == (7, 6, 6)
    assert g.num_poses == 6 and g.num_edges == 7 and g.vertex_ids.tolist() == list(range(6))
    g.add_edge(5, 0, se3_identity(dtype=F64), 2.0 * torch.eye(6, dtype=F64))
    assert g.num_edges == 8 and float(g.information[-1, 0, 0]) == 2.0
    g2 = g.with_poses(torch.zeros(6, 7, dtype=F64) + se3_identity(dtype=F64))
    assert g2.ii is g.ii and float(graph_chi2(g2)) >= 0.0
    h = PoseGraph.from_lists([[0, 0, 0, 0, 0, 0, 2.0], [1, 0, 0, 0, 0, 0, 1]],
                             [(0, 1, [1, 0, 0, 0, 0, 0, 1])])
    assert torch.allclose(h.poses[0], se3_identity(dtype=F64))  # quaternion normalised
    assert h.to(dtype=torch.float32).poses.dtype == torch.float32
    assert "PoseGraph(num_poses=2" in repr(h)


def test_validation_errors_name_the_problem():
    g = _random_graph()
    with pytest.raises(ValueError, match=r"poses must have shape \(N, 7\)"):
        PoseGraph(g.poses[:, :6], g.ii, g.jj, g.measurements, g.information)
    with pytest.raises(ValueError, match=r"measurements must have shape \(E, 7\)"):
        PoseGraph(g.poses, g.ii, g.jj, g.measurements[:3], g.information)
    with pytest.raises(ValueError, match=r"information must have shape \(E, 6, 6\)"):
        PoseGraph(g.poses, g.ii, g.jj, g.measurements, g.information[:, :3])
    with pytest.raises(ValueError, match=r"edge 2: jj\[2\] = 9 is not a pose index"):
        PoseGraph(g.poses, g.ii, torch.tensor([1, 2, 9, 4, 5, 3, 5]), g.measurements, g.information)
    with pytest.raises(ValueError, match="connects pose 1 to itself"):
        PoseGraph(g.poses, g.ii, torch.tensor([1, 1, 3, 4, 5, 3, 5]), g.measurements, g.information)
    bad = g.poses.clone()
    bad[2, 0] = float("nan")
    with pytest.raises(ValueError, match=r"poses\[2\] has a non-finite value"):
        PoseGraph(bad, g.ii, g.jj, g.measurements, g.information)
    bad = g.measurements.clone()
    bad[1, 3:] *= 2
    with pytest.raises(ValueError, match=r"measurements\[1\] has a quaternion of norm 2"):
        PoseGraph(g.poses, g.ii, g.jj, bad, g.information)
    info = g.information.clone()
    info[4] = -torch.eye(6, dtype=F64)
    with pytest.raises(ValueError, match=r"information\[4\] .* not symmetric positive definite"):
        PoseGraph(g.poses, g.ii, g.jj, g.measurements, info).validate()
    with pytest.raises(ValueError, match="not symmetric positive definite"):
        g.add_edge(0, 2, se3_identity(dtype=F64), torch.diag(torch.tensor([1.0, 1, 1, 1, 1, 0], dtype=F64)))
    assert g.num_edges == 7  # a rejected edge leaves the graph unchanged
    with pytest.raises(ValueError, match="chart must be one of"):
        PoseGraph(g.poses, g.ii, g.jj, g.measurements, g.information, chart="quat")


def test_residual_is_zero_for_exact_measurements():
    g = _random_graph(seed=1)
    exact = se3_between(g.poses[g.ii], g.poses[g.jj])
    for chart in ("se3", "r3so3"):
        r, _ = edge_residuals(g.poses, g.ii, g.jj, exact, chart)
        assert float(r.abs().max()) < 1e-12
    # se3 chart: r = Log(z^-1 T_i^-1 T_j)
    r, _ = edge_residuals(g.poses, g.ii, g.jj, g.measurements)
    ref = se3_log(se3_compose(se3_compose(se3_exp(-se3_log(g.measurements)), se3_between(g.poses[g.ii],
                                                                                         g.poses[g.jj])),
                              se3_identity(dtype=F64)))
    assert torch.allclose(r, ref, atol=1e-10)


@pytest.mark.parametrize("chart", ["se3", "r3so3"])
@pytest.mark.parametrize("rot", [1e-6, 1.0, 2.5])
def test_jacobians_match_finite_differences(chart, rot):
    g = _random_graph(seed=2, rot=rot)
    P, ii, jj, Z = g.poses, g.ii, g.jj, g.measurements
    r, D = edge_residuals(P, ii, jj, Z, chart)
    Ji, Jj = edge_jacobians(P, ii, jj, D, r, chart)
    h = 1e-6
    for e in range(g.num_edges):
        for which, J in (("i", Ji), ("j", Jj)):
            pose = int(ii[e] if which == "i" else jj[e])
            cols = []
            for k in range(6):
                d = torch.zeros(6, dtype=F64)
                d[k] = h
                Pp, Pm = P.clone(), P.clone()
                Pp[pose] = se3_compose(P[pose], se3_exp(d))
                Pm[pose] = se3_compose(P[pose], se3_exp(-d))
                rp = edge_residuals(Pp, ii[e:e + 1], jj[e:e + 1], Z[e:e + 1], chart)[0]
                rm = edge_residuals(Pm, ii[e:e + 1], jj[e:e + 1], Z[e:e + 1], chart)[0]
                cols.append(((rp - rm) / (2 * h))[0])
            assert torch.allclose(J[e], torch.stack(cols, -1), atol=1e-6), (e, which)


def test_planar_detection():
    g = _random_graph()
    assert not g.is_planar()
    th = torch.tensor([0.1, -0.5, 2.0], dtype=F64)
    P = torch.zeros(3, 7, dtype=F64)
    P[:, 0] = torch.tensor([0.0, 1.0, 2.0])
    P[:, 5], P[:, 6] = torch.sin(th / 2), torch.cos(th / 2)
    h = PoseGraph.from_lists(P, [(0, 1, se3_between(P[0], P[1])), (1, 2, se3_between(P[1], P[2]))])
    assert h.is_planar()
    h.information[0, 0, 2] = h.information[0, 2, 0] = 0.1  # couples x with z
    assert not h.is_planar()


def test_kernels_rho_weight_and_derivative():
    s0 = torch.tensor([0.0, 0.5, 3.0, 12.0, 50.0, 1e4], dtype=F64)
    s = s0.clone().requires_grad_()
    for kern in (Huber(2.0), Cauchy(2.0), Tukey(3.0), GemanMcClure(2.0)):
        rho, w = kern(s)
        (grad,) = torch.autograd.grad(rho.sum(), s)
        assert torch.allclose(w, grad, atol=1e-12), kern  # w = rho'(s)
        rho, w = kern(s0)
        assert torch.allclose(rho[:2], s0[:2], rtol=0.3)  # rho(s) ~ s for small s
        assert float(w[0]) == pytest.approx(1.0)
        assert bool((w[1:] <= 1.0).all()) and bool((w >= 0).all())
    assert float(Huber(2.0)(torch.tensor([16.0]))[0][0]) == pytest.approx(2 * 2 * 4 - 4)
    assert float(Cauchy(1.0)(torch.tensor([math.e - 1]))[0][0]) == pytest.approx(1.0)
    assert float(Tukey(1.0)(torch.tensor([5.0]))[1][0]) == 0.0
    assert make_kernel(None) is None and make_kernel("none") is None
    assert isinstance(make_kernel("Huber"), Huber) and make_kernel("cauchy", 1.5).width == 1.5
    with pytest.raises(ValueError, match="unknown robust kernel"):
        make_kernel("welsch")
    with pytest.raises(ValueError, match="width must be > 0"):
        Huber(0.0)


def test_sparse_assembly_matches_dense_normal_equations():
    g = _random_graph(seed=3)
    r, D = edge_residuals(g.poses, g.ii, g.jj, g.measurements)
    Ji, Jj = edge_jacobians(g.poses, g.ii, g.jj, D, r)
    free = torch.ones(6, dtype=torch.bool)
    free[0] = False
    pat = build_pattern(g.ii, g.jj, free, 6)
    J = torch.cat([Ji, Jj], -1)
    Hb = J.mT @ g.information @ J
    gb = (J.mT @ g.information @ r[..., None])[..., 0]
    vals, grad = assemble_blocks(pat, Hb.view(-1, 2, 6, 2, 6).transpose(2, 3), gb.view(-1, 2, 6))
    # dense reference: stack the full Jacobian (E*6, N*6), drop pose 0
    Jfull = torch.zeros(g.num_edges * 6, 36, dtype=F64)
    for e in range(g.num_edges):
        Jfull[6 * e:6 * e + 6, 6 * g.ii[e]:6 * g.ii[e] + 6] += Ji[e]
        Jfull[6 * e:6 * e + 6, 6 * g.jj[e]:6 * g.jj[e] + 6] += Jj[e]
    W = torch.block_diag(*g.information)
    Href = (Jfull.T @ W @ Jfull)[6:, 6:]
    gref = (Jfull.T @ W @ r.reshape(-1))[6:]
    H = to_dense(pat, vals)
    assert torch.allclose(H, Href, atol=1e-9) and torch.allclose(grad, gref, atol=1e-9)
    assert torch.allclose(H, H.T, atol=1e-12)


@pytest.mark.parametrize("k", [6, 3])
def test_sparse_cholesky_matches_dense_solve(k):
    pytest.importorskip("scipy")
    from slam.graph.cholesky import NotPositiveDefiniteError, SymbolicCholesky

    g = torch.Generator().manual_seed(4)
    n = 150
    ii = torch.cat([torch.arange(n - 1), torch.randint(0, n, (200,), generator=g)])
    jj = torch.cat([torch.arange(1, n), torch.randint(0, n, (200,), generator=g)])
    keep = ii != jj
    ii, jj = ii[keep], jj[keep]
    free = torch.ones(n, dtype=torch.bool)
    free[0] = False
    pat = build_pattern(ii, jj, free, k)
    J = torch.randn(ii.shape[0], k, 2 * k, generator=g, dtype=F64)
    vals, _ = assemble_blocks(pat, (J.mT @ J).view(-1, 2, k, 2, k).transpose(2, 3),
                              torch.zeros(ii.shape[0], 2, k, dtype=F64))
    vals = vals.clone()
    vals[pat.diag_pos] += 1e-3  # H = sum J^T J + damping: SPD
    b = torch.randn(pat.size, generator=g, dtype=F64)
    sym = SymbolicCholesky(pat)
    assert len(sym.groups) < sym.num_supernodes <= pat.num_vars  # batched groups and supernodes
    x = sym.factor(vals).solve(b)
    ref = torch.linalg.solve(to_dense(pat, vals), b)
    assert torch.allclose(x, ref, atol=1e-8 * float(ref.abs().max()))
    x_np = sym.factor(vals.numpy()).solve(b.numpy())  # numpy in, numpy out
    assert abs(x_np - ref.numpy()).max() < 1e-8 * float(ref.abs().max())
    bad = vals.clone()
    bad[pat.diag_pos[7]] = -1.0
    with pytest.raises(NotPositiveDefiniteError):
        sym.factor(bad)
