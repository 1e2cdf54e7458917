"""The torch reference of the pose-graph maths (slam.graph.fused, behind slam.graph.costs) against independent
references: slam.lie's group operations composed one by one, their autograd Jacobians, and float64
gradcheck / gradgradcheck of the fused functions themselves (at generic edges, an exact edge, the series
branches and near pi)."""
import math

import pytest
import torch

from slam.graph.costs import edge_jacobians, edge_residuals
from slam.graph.fused import normal_blocks, se3_adjoint_t, se3_jacobians_t, se3_residuals, se3_retract
from slam.lie import se3_between, se3_compose, se3_exp, se3_inv, se3_log, so3_log

F64 = torch.float64


def _edges(seed=3, N=12, E=40):
    """Random poses and measurements with an exact edge, one near pi and edges in the series branches."""
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
    dz[4, 3:] = 0.0  # no rotation error, translation error only
    return P, ii, jj, se3_compose(se3_between(P[ii], P[jj]), se3_exp(dz))


def _lie_residuals(P, ii, jj, Z, chart):
    """r from slam.lie alone: D = z^-1 T_i^-1 T_j, then Log (or [t, Log_SO3])."""
    D = se3_compose(se3_inv(Z), se3_between(P[ii], P[jj]))
    return se3_log(D) if chart == "se3" else torch.cat([D[:, :3], so3_log(D[:, 3:])], -1)


def _autograd_jacobians(P, ii, jj, Z, chart):
    """(J_i, J_j) of _lie_residuals w.r.t. right perturbations, by autograd through slam.lie."""
    E = ii.shape[0]
    d = torch.zeros(E, 12, dtype=F64, requires_grad=True)
    Pe = torch.cat([se3_compose(P[ii], se3_exp(d[:, :6])), se3_compose(P[jj], se3_exp(d[:, 6:]))])
    r = _lie_residuals(Pe, torch.arange(E), torch.arange(E) + E, Z, chart)
    J = torch.stack([torch.autograd.grad(r[:, k].sum(), d, retain_graph=True)[0] for k in range(6)], 1)
    return J[:, :, :6], J[:, :, 6:]


@pytest.mark.parametrize("chart", ["se3", "r3so3"])
def test_residuals_and_jacobians_equal_slam_lie_and_its_autograd(chart):
    P, ii, jj, Z = _edges()
    r, D = edge_residuals(P, ii, jj, Z, chart)
    r_lie = _lie_residuals(P, ii, jj, Z, chart)
    assert torch.allclose(r, r_lie, atol=1e-12, rtol=0)
    assert float(r[0].abs().max()) < 1e-14 and float(r[1, 3:].norm()) == pytest.approx(math.pi - 1e-3, abs=1e-6)
    Ji, Jj = edge_jacobians(P, ii, jj, D, r, chart)
    Ai, Aj = _autograd_jacobians(P, ii, jj, Z, chart)
    assert torch.allclose(Ji, Ai, atol=1e-9, rtol=0) and torch.allclose(Jj, Aj, atol=1e-9, rtol=0)


@pytest.mark.parametrize("chart", ["se3", "r3so3"])
def test_normal_blocks_are_the_weighted_products_of_the_jacobians(chart):
    P, ii, jj, Z = _edges()
    E = ii.shape[0]
    g = torch.Generator().manual_seed(4)
    zinv = se3_inv(Z)
    r, aux = se3_residuals(P, ii, jj, zinv, chart)
    neg = -se3_adjoint_t(zinv) if chart == "se3" else None
    JT = se3_jacobians_t(r, aux, neg, poses=P, ii=ii, jj=jj)
    Ji, Jj = _autograd_jacobians(P, ii, jj, Z, chart)
    W = torch.randn(E, 6, 6, generator=g, dtype=F64)
    info = W @ W.mT + torch.eye(6, dtype=F64)
    w = torch.rand(E, generator=g, dtype=F64)
    blocks, gb = normal_blocks(JT, torch.linalg.cholesky(info).contiguous(), w, ws={})
    J = torch.cat([Ji, Jj], -1)
    Hr = J.mT @ (w[:, None, None] * info) @ J
    gr = (J.mT @ (w[:, None, None] * info) @ r[:, :, None])[..., 0]
    assert torch.allclose(blocks, Hr.view(E, 2, 6, 2, 6).permute(0, 1, 3, 2, 4).reshape(E, 4, 6, 6), atol=1e-8)
    assert torch.allclose(gb, gr.view(E, 2, 6), atol=1e-8)


def test_retraction_equals_compose_exp():
    P, _, _, _ = _edges()
    step = torch.randn(P.shape[0], 6, generator=torch.Generator().manual_seed(5), dtype=F64)
    step[0] = 0.0
    step[1] = 1e-9
    step[2, 3:] = torch.tensor([0.0, 0.0, math.pi - 1e-4])
    step[3, 3:] = 0.0
    assert torch.allclose(se3_retract(P, step), se3_compose(P, se3_exp(step)), atol=1e-12, rtol=0)
    assert torch.equal(se3_retract(P, step)[0], P[0])


@pytest.mark.parametrize("chart", ["se3", "r3so3"])
def test_fused_residuals_pass_gradcheck_and_gradgradcheck(chart):
    """float64 gradcheck of r(poses, z^-1) on every kind of edge, and second order (the implicit gradients
    of slam.graph.implicit differentiate the cost's gradient), including the exact edge r = 0."""
    P, ii, jj, Z = _edges(E=6, N=4)
    zinv = se3_inv(Z)

    def f(P_, zinv_):
        return se3_residuals(P_, ii, jj, zinv_, chart)[0]

    args = (P.clone().requires_grad_(True), zinv.clone().requires_grad_(True))
    assert torch.autograd.gradcheck(f, args, atol=1e-7, rtol=1e-6, fast_mode=True)
    assert torch.autograd.gradgradcheck(f, args, atol=1e-6, rtol=1e-5, fast_mode=True)


def test_retraction_passes_gradcheck_at_zero_and_away_from_it():
    P, _, _, _ = _edges(N=5)
    xi = torch.randn(5, 6, generator=torch.Generator().manual_seed(6), dtype=F64) * 0.5
    xi[0] = 0.0  # exactly no step: the derivative the implicit gradients need
    xi[1, 3:] = 1e-6  # series branch
    args = (P.clone().requires_grad_(True), xi.requires_grad_(True))
    assert torch.autograd.gradcheck(se3_retract, args, atol=1e-7, rtol=1e-6)
    assert torch.autograd.gradgradcheck(se3_retract, args, atol=1e-6, rtol=1e-5, fast_mode=True)


def test_the_identity_has_finite_exact_derivatives():
    """At an exactly met edge and a zero step, |v| = 0 and theta = 0: the derivatives exist (the series
    branches) and equal slam.lie's: d r / d right perturbation of T_j is the identity there."""
    P, ii, jj, _ = _edges(N=4, E=5)
    Z = se3_between(P[ii], P[jj])  # every edge exact
    d = torch.zeros(5, 6, dtype=F64, requires_grad=True)
    Pj = se3_retract(P[jj], d)
    r = se3_residuals(torch.cat([P[ii], Pj]), torch.arange(5), torch.arange(5) + 5, se3_inv(Z))[0]
    J = torch.stack([torch.autograd.grad(r[:, k].sum(), d, retain_graph=True)[0] for k in range(6)], 1)
    assert torch.isfinite(J).all()
    assert torch.allclose(J, torch.eye(6, dtype=F64).expand(5, 6, 6), atol=1e-12)
