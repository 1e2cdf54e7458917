"""slam.lie.se3_to_kornia / se3_from_kornia: our (..., 7) [t, q_xyzw] poses and kornia's Se3 (w-first
quaternions) at the boundary: round trips, composition, inversion, log/exp, adjoint, the action on points,
gradients through the conversion, and the optimised poses of a pose graph."""
import math

import pytest
import torch

from slam.lie import (
    se3_act,
    se3_adjoint,
    se3_compose,
    se3_exp,
    se3_from_kornia,
    se3_inv,
    se3_log,
    se3_to_kornia,
    se3_to_matrix,
)

liegroup = pytest.importorskip("kornia.geometry.liegroup")
F64 = torch.float64


def _poses(n=20, seed=0):
    g = torch.Generator().manual_seed(seed)
    xi = torch.randn(n, 6, generator=g, dtype=F64)
    xi[:, 3:] *= 0.9  # angles up to ~3 rad (kornia's near-pi log is less precise than ours)
    xi[0] = 0.0  # the identity
    xi[1, 3:] = torch.tensor([0.0, 0.0, math.pi - 1e-3], dtype=F64)
    return xi, se3_exp(xi)


def test_round_trips_are_exact_and_keep_the_batch_shape():
    _, P = _poses()
    T = se3_to_kornia(P)
    assert isinstance(T, liegroup.Se3) and T.t.shape == (20, 3) and T.r.q.data.shape == (20, 4)
    assert torch.equal(T.r.q.data[:, 0], P[:, 6]) and torch.equal(T.r.q.data[:, 1:], P[:, 3:6])  # w first
    assert torch.equal(se3_from_kornia(T), P)
    P3 = P.reshape(4, 5, 7)
    assert torch.equal(se3_from_kornia(se3_to_kornia(P3)), P3)
    neg = torch.cat([P[:, :3], -P[:, 3:]], -1)  # q and -q: the same rotation, kept as given
    assert torch.equal(se3_from_kornia(se3_to_kornia(neg)), neg)
    K = liegroup.Se3.exp(torch.randn(6, 6, generator=torch.Generator().manual_seed(1), dtype=F64))
    back = se3_to_kornia(se3_from_kornia(K))
    assert torch.equal(back.t, K.t) and torch.equal(back.r.q.data, K.r.q.data)


def test_group_operations_agree():
    xi, P = _poses()
    _, Q = _poses(seed=2)
    A, B = se3_to_kornia(P), se3_to_kornia(Q)
    assert torch.allclose(se3_from_kornia(A * B), se3_compose(P, Q), atol=1e-12, rtol=0)
    assert torch.allclose(se3_from_kornia(A.inverse()), se3_inv(P), atol=1e-12, rtol=0)
    assert torch.allclose(A.log(), se3_log(P), atol=1e-9, rtol=0)  # tangent [rho, phi] in both
    assert torch.allclose(A.log(), xi, atol=1e-9, rtol=0)
    assert torch.allclose(se3_from_kornia(liegroup.Se3.exp(xi)), P, atol=1e-12, rtol=0)
    assert torch.allclose(A.adjoint(), se3_adjoint(P), atol=1e-12, rtol=0)
    assert torch.allclose(A.matrix(), se3_to_matrix(P), atol=1e-12, rtol=0)
    pts = torch.randn(20, 3, generator=torch.Generator().manual_seed(3), dtype=F64)
    assert torch.allclose(A * pts, se3_act(P, pts), atol=1e-12, rtol=0)


def test_gradients_flow_through_the_conversions():
    _, P = _poses(n=4)
    P = P.clone().requires_grad_(True)
    pts = torch.randn(4, 3, generator=torch.Generator().manual_seed(4), dtype=F64)

    def through_kornia(p):
        return se3_from_kornia(se3_to_kornia(p) * se3_to_kornia(p))[:, :3] + se3_to_kornia(p) * pts

    assert torch.autograd.gradcheck(through_kornia, (P,), atol=1e-8, rtol=1e-6)
    # along the group (right perturbations; off it, kornia rotates by a quaternion's direction, we by the
    # quaternion as given) the derivatives equal ours
    d = torch.zeros(4, 6, dtype=F64, requires_grad=True)
    Pd = se3_compose(P.detach(), se3_exp(d))
    (ref,) = torch.autograd.grad((se3_compose(Pd, Pd)[:, :3] + se3_act(Pd, pts)).sum(), d)
    Pd = se3_compose(P.detach(), se3_exp(d))
    (got,) = torch.autograd.grad(through_kornia(Pd).sum(), d)
    assert torch.allclose(got, ref, atol=1e-12)


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match=r"\(\.\.\., 7\)"):
        se3_to_kornia(torch.zeros(3, 6))
    with pytest.raises(TypeError, match="kornia.geometry.liegroup.Se3, got Tensor"):
        se3_from_kornia(torch.zeros(3, 7))


def test_optimised_pose_graph_poses_convert():
    from slam.graph import PoseGraph, optimize

    _, P = _poses(n=6)
    ii, jj = torch.arange(5), torch.arange(1, 6)
    Z = se3_compose(se3_inv(P[ii]), P[jj])
    res = optimize(PoseGraph(P, ii, jj, Z, torch.eye(6, dtype=F64).expand(5, 6, 6)))
    assert torch.allclose((se3_to_kornia(res.graph.poses[:-1]).inverse() * se3_to_kornia(res.graph.poses[1:])).log(),
                          se3_log(Z), atol=1e-9)
