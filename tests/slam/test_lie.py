"""SO(3)/SE(3) in slam.lie: identities, independent references (matrix_exp, kornia) and finite differences."""
import math

import pytest
import torch

from slam.lie import (
    quat_angle,
    quat_mul,
    quat_normalize,
    quat_rotate,
    quat_to_rotmat,
    rotmat_to_quat,
    se3_act,
    se3_ad,
    se3_adjoint,
    se3_between,
    se3_compose,
    se3_exp,
    se3_from_matrix,
    se3_identity,
    se3_inv,
    se3_left_jacobian_inv,
    se3_log,
    se3_right_jacobian_inv,
    se3_to_matrix,
    so3_exp,
    so3_hat,
    so3_left_jacobian,
    so3_left_jacobian_inv,
    so3_log,
    so3_right_jacobian_inv,
)

F64 = torch.float64


def se3_hat(xi):
    """4x4 Lie-algebra matrices ``(..., 4, 4)`` of tangent vectors ``[rho, phi] (..., 6)``."""
    top = torch.cat([so3_hat(xi[..., 3:]), xi[..., :3, None]], dim=-1)
    return torch.cat([top, torch.zeros(xi.shape[:-1] + (1, 4), dtype=xi.dtype)], dim=-2)


def _tangents(n=64, seed=0, dtype=F64):
    """Random tangent vectors incl. tiny, zero and near-pi rotations."""
    g = torch.Generator().manual_seed(seed)
    xi = torch.randn(n, 6, generator=g, dtype=F64)
    xi[: n // 4, 3:] *= 1e-7  # near the identity
    xi[n // 4: n // 2, 3:] *= 1e-3
    axis = torch.nn.functional.normalize(torch.randn(n // 4, 3, generator=g, dtype=F64), dim=-1)
    xi[n // 2: 3 * n // 4, 3:] = axis * (math.pi - 10.0 ** -torch.linspace(2, 6, n // 4, dtype=F64))[:, None]
    xi[0] = 0.0
    return xi.to(dtype)


def _assert_same_pose(a, b, atol):
    # q and -q are the same rotation
    dq = torch.minimum((a[..., 3:] - b[..., 3:]).abs().amax(-1), (a[..., 3:] + b[..., 3:]).abs().amax(-1))
    assert float(dq.max()) < atol
    assert float((a[..., :3] - b[..., :3]).abs().max()) < atol


@pytest.mark.parametrize("dtype,atol", [(torch.float64, 1e-10), (torch.float32, 2e-4)])
def test_log_exp_roundtrip(dtype, atol):
    xi = _tangents(dtype=dtype)
    back = se3_log(se3_exp(xi))
    assert back.dtype == dtype and back.shape == xi.shape
    assert float((back - xi).abs().max()) < atol * 10
    phi = xi[:, 3:]
    assert float((so3_log(so3_exp(phi)) - phi).abs().max()) < atol * 10


def test_exp_log_roundtrip_on_poses():
    p = se3_exp(_tangents(seed=1))
    _assert_same_pose(se3_exp(se3_log(p)), p, 1e-10)
    # exactly pi: log gives an angle of pi (either sign of the axis) and exp maps back
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64)  # rotation of pi about x
    phi = so3_log(q)
    assert abs(float(phi.norm()) - math.pi) < 1e-12
    R = quat_to_rotmat(so3_exp(phi))
    assert torch.allclose(R, quat_to_rotmat(q), atol=1e-12)


def test_inverse_and_compose_identities():
    a, b, c = (se3_exp(_tangents(seed=s)) for s in (2, 3, 4))
    eye = se3_identity(a.shape[0], dtype=F64)
    _assert_same_pose(se3_compose(a, se3_inv(a)), eye, 1e-12)
    _assert_same_pose(se3_compose(se3_inv(a), a), eye, 1e-12)
    _assert_same_pose(se3_compose(se3_compose(a, b), c), se3_compose(a, se3_compose(b, c)), 1e-12)
    _assert_same_pose(se3_between(a, b), se3_compose(se3_inv(a), b), 1e-12)
    M = se3_to_matrix(a) @ se3_to_matrix(b)
    assert torch.allclose(se3_to_matrix(se3_compose(a, b)), M, atol=1e-12)
    assert torch.allclose(se3_to_matrix(se3_inv(a)), torch.linalg.inv(se3_to_matrix(a)), atol=1e-10)


def test_exp_matches_matrix_exponential():
    xi = _tangents(seed=5)
    T = torch.linalg.matrix_exp(se3_hat(xi))
    assert torch.allclose(se3_to_matrix(se3_exp(xi)), T, atol=1e-10)
    R = torch.linalg.matrix_exp(so3_hat(xi[:, 3:]))
    assert torch.allclose(quat_to_rotmat(so3_exp(xi[:, 3:])), R, atol=1e-10)


def test_act_matches_matrix_and_quaternion_product():
    p = se3_exp(_tangents(seed=6))
    pts = torch.randn(p.shape[0], 3, dtype=F64)
    T = se3_to_matrix(p)
    ref = (T[:, :3, :3] @ pts[:, :, None])[..., 0] + T[:, :3, 3]
    assert torch.allclose(se3_act(p, pts), ref, atol=1e-12)
    v = torch.cat([pts, torch.zeros(pts.shape[0], 1, dtype=F64)], -1)
    q = p[:, 3:]
    qv = quat_mul(quat_mul(q, v), torch.cat([-q[:, :3], q[:, 3:]], -1))
    assert torch.allclose(quat_rotate(q, pts), qv[:, :3], atol=1e-12)
    # one pose applied to a cloud broadcasts
    assert se3_act(p[:1], pts).shape == pts.shape


def test_matrix_quaternion_roundtrip_all_branches():
    xi = _tangents(seed=7)
    q = so3_exp(xi[:, 3:])
    q2 = rotmat_to_quat(quat_to_rotmat(q))
    assert torch.allclose(quat_normalize(q), q2, atol=1e-12)
    p = se3_exp(xi)
    _assert_same_pose(se3_from_matrix(se3_to_matrix(p)), p, 1e-12)


def test_adjoint_identity():
    X = se3_exp(_tangents(seed=8))
    xi = torch.randn(X.shape[0], 6, dtype=F64) * 0.3
    lhs = se3_compose(X, se3_exp(xi))
    rhs = se3_compose(se3_exp((se3_adjoint(X) @ xi[:, :, None])[..., 0]), X)
    _assert_same_pose(lhs, rhs, 1e-10)
    # Ad is a homomorphism and the 4x4 form agrees: Ad(X) xi = vee(T hat(xi) T^-1)
    Y = se3_exp(_tangents(seed=9))
    assert torch.allclose(se3_adjoint(se3_compose(X, Y)), se3_adjoint(X) @ se3_adjoint(Y), atol=1e-10)
    T = se3_to_matrix(X)
    W = T @ se3_hat(xi) @ torch.linalg.inv(T)
    v = torch.cat([W[:, :3, 3], torch.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], -1)], -1)
    assert torch.allclose((se3_adjoint(X) @ xi[:, :, None])[..., 0], v, atol=1e-10)
    # small adjoint = derivative of Ad(exp(t a)) at 0; ad(a) b = -ad(b) a
    a, b = torch.randn(2, 6, dtype=F64)
    assert torch.allclose(se3_ad(a) @ b, -(se3_ad(b) @ a), atol=1e-14)
    h = 1e-6
    fd = (se3_adjoint(se3_exp(h * a)) - se3_adjoint(se3_exp(-h * a))) / (2 * h)
    assert torch.allclose(fd, se3_ad(a), atol=1e-8)


def _fd_jacobian(f, x, h=1e-6):
    cols = []
    for k in range(x.shape[-1]):
        e = torch.zeros_like(x)
        e[..., k] = h
        cols.append((f(x + e) - f(x - e)) / (2 * h))
    return torch.stack(cols, -1)


@pytest.mark.parametrize("scale", [1e-9, 1e-3, 0.5, 2.0, 3.1])
def test_so3_and_se3_jacobians_vs_finite_differences(scale):
    g = torch.Generator().manual_seed(10)
    xi = torch.randn(8, 6, generator=g, dtype=F64)
    xi[:, 3:] = torch.nn.functional.normalize(xi[:, 3:], dim=-1) * scale
    phi = xi[:, 3:]
    # left: exp(phi + d) = exp(J_l d) exp(phi); right: exp(phi + d) = exp(phi) exp(J_r d)
    Jl = _fd_jacobian(lambda d: so3_log(quat_mul(so3_exp(phi + d), so3_exp(-phi))), torch.zeros_like(phi))
    Jr = _fd_jacobian(lambda d: so3_log(quat_mul(so3_exp(-phi), so3_exp(phi + d))), torch.zeros_like(phi))
    assert torch.allclose(so3_left_jacobian(phi), Jl, atol=1e-8)
    eye3 = torch.eye(3, dtype=F64).expand(8, 3, 3)
    assert torch.allclose(so3_left_jacobian_inv(phi) @ Jl, eye3, atol=1e-7)
    assert torch.allclose(so3_right_jacobian_inv(phi) @ Jr, eye3, atol=1e-7)
    X = se3_exp(xi)
    JlS = _fd_jacobian(lambda d: se3_log(se3_compose(se3_exp(xi + d), se3_inv(X))), torch.zeros_like(xi))
    assert torch.allclose(se3_left_jacobian_inv(xi) @ JlS, torch.eye(6, dtype=F64).expand(8, 6, 6), atol=1e-7)
    # J_r^-1: derivative of log under a right perturbation
    Jri = _fd_jacobian(lambda d: se3_log(se3_compose(X, se3_exp(d))), torch.zeros_like(xi))
    assert torch.allclose(se3_right_jacobian_inv(xi), Jri, atol=1e-7)


def test_jacobians_float32_close_to_float64():
    xi = _tangents(seed=11)
    xi = xi[xi[:, 3:].norm(dim=-1) < 3.0]  # J^-1 is singular at 2 pi; stay clear of pi in float32
    for f in (se3_left_jacobian_inv, se3_right_jacobian_inv):
        assert torch.allclose(f(xi.float()).double(), f(xi), atol=2e-4)


def test_autograd_is_finite_at_identity_and_gradcheck():
    xi = torch.zeros(2, 6, dtype=F64, requires_grad=True)
    out = se3_log(se3_exp(xi)).sum() + se3_right_jacobian_inv(xi).sum() + se3_left_jacobian_inv(xi).sum()
    out.backward()
    assert torch.isfinite(xi.grad).all()
    x = (torch.randn(2, 6, dtype=F64) * 0.5).requires_grad_()
    assert torch.autograd.gradcheck(lambda v: se3_log(se3_exp(v)), (x,))
    assert torch.autograd.gradcheck(se3_left_jacobian_inv, (x,))


def test_broadcast_and_shape_errors():
    a = se3_exp(torch.randn(4, 1, 6, dtype=F64))
    b = se3_exp(torch.randn(1, 5, 6, dtype=F64))
    assert se3_compose(a, b).shape == (4, 5, 7)
    assert se3_right_jacobian_inv(torch.randn(2, 3, 6)).shape == (2, 3, 6, 6)
    with pytest.raises(ValueError, match=r"\(\.\.\., 6\)"):
        se3_exp(torch.zeros(3, 5))
    with pytest.raises(ValueError, match=r"\(\.\.\., 7\)"):
        se3_inv(torch.zeros(3, 6))


def test_cross_check_with_kornia():
    liegroup = pytest.importorskip("kornia.geometry.liegroup")
    from kornia.geometry.quaternion import Quaternion

    xi = _tangents(seed=13)
    xi = xi[xi[:, 3:].norm(dim=-1) < 3.0]  # kornia's own near-pi branch is less precise
    k = liegroup.Se3.exp(xi)  # kornia: tangent [upsilon (translation), omega], quaternion wxyz
    ours = se3_exp(xi)
    q_wxyz = k.r.q.data
    kornia_pose = torch.cat([k.t.data, q_wxyz[:, 1:], q_wxyz[:, :1]], -1)
    _assert_same_pose(ours, kornia_pose, 1e-9)
    assert torch.allclose(k.matrix().detach(), se3_to_matrix(ours), atol=1e-9)
    assert torch.allclose(k.adjoint().detach(), se3_adjoint(ours), atol=1e-9)
    # kornia log of our pose (wxyz quaternion) gives our tangent
    q = ours[:, 3:]
    ks = liegroup.Se3(Quaternion(torch.cat([q[:, 3:], q[:, :3]], -1)), ours[:, :3])
    assert torch.allclose(ks.log().detach(), se3_log(ours), atol=1e-8)
    assert torch.allclose(liegroup.So3.hat(xi[:, 3:]), so3_hat(xi[:, 3:]))


def test_single_quaternion_rotation_matrix_is_the_batched_one_bit_for_bit():
    """One float64 quaternion is computed from Python floats: the same bits as the tensor formula on 2000
    rotations (non-unit ones included), and the matrix of a hand-computed case."""
    g = torch.Generator().manual_seed(0)
    q = torch.randn(2000, 4, generator=g, dtype=torch.float64)
    q[:1000] /= q[:1000].norm(dim=1, keepdim=True)
    ref = quat_to_rotmat(q)
    assert all(torch.equal(quat_to_rotmat(qi), ri) for qi, ri in zip(q, ref))
    half = math.sqrt(0.5)  # 90 degrees about z: x -> y
    R = quat_to_rotmat(torch.tensor([0.0, 0.0, half, half], dtype=torch.float64))
    assert torch.allclose(R, torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64), atol=1e-15)
    z = torch.tensor([0.1, 0.2, 0.3, 0.9], dtype=torch.float64, requires_grad=True)
    quat_to_rotmat(z).sum().backward()  # a quaternion that requires grad takes the tensor formula
    assert z.grad is not None and torch.isfinite(z.grad).all()


def test_quat_angle_against_hand_values_and_the_logarithm():
    q = torch.tensor([[0.0, 0.0, math.sin(0.35), math.cos(0.35)],  # 0.7 rad about z
                      [0.0, 0.0, 0.0, -1.0],  # the identity, negative sign
                      [1.0, 0.0, 0.0, 0.0],  # pi about x
                      [0.0, 2e-9, 0.0, 1.0]], dtype=torch.float64)  # 4e-9 rad: acos would lose it
    assert torch.allclose(quat_angle(q), torch.tensor([0.7, 0.0, math.pi, 4e-9], dtype=torch.float64),
                          rtol=1e-12, atol=0)
    r = so3_exp(torch.randn(500, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64))
    assert torch.allclose(quat_angle(r), so3_log(r).norm(dim=-1), atol=1e-12)
    assert torch.allclose(quat_angle(-3.0 * r), quat_angle(r), atol=1e-12)  # sign and scale do not matter
