"""SO(3) and SE(3) in plain torch: poses ``(..., 7) = [tx, ty, tz, qx, qy, qz, qw]`` (TUM order, Hamilton unit
quaternions, scalar last), rotations ``(..., 4) = [qx, qy, qz, qw]``, SE(3) tangents ``(..., 6) = [rho, phi]``
(translation first), SO(3) tangents ``(..., 3)``; ``compose(X, exp(xi))`` is a right perturbation.

Every function broadcasts over leading shapes, works in float32 and float64 on its inputs' device, and is
autograd-safe (no ``0/0``) near the identity and near a rotation of pi.

Example:
    >>> xi = torch.tensor([[0.1, -0.2, 0.3, 0.4, 0.5, -0.6]], dtype=torch.float64)
    >>> pose = se3_exp(xi)
    >>> pose.shape
    torch.Size([1, 7])
    >>> torch.allclose(se3_log(pose), xi)
    True
"""
from __future__ import annotations

import torch

Tensor = torch.Tensor

__all__ = [
    "quat_angle", "quat_conj", "quat_mul", "quat_normalize", "quat_rotate", "quat_to_rotmat", "rotmat_project",
    "rotmat_to_quat", "se3_act", "se3_ad", "se3_adjoint", "se3_between", "se3_compose", "se3_exp", "se3_from_kornia",
    "se3_from_matrix", "se3_identity", "se3_inv", "se3_left_jacobian_inv", "se3_log", "se3_normalize",
    "se3_right_jacobian_inv", "se3_to_kornia", "se3_to_matrix", "so3_exp", "so3_hat", "so3_left_jacobian",
    "so3_left_jacobian_inv", "so3_log", "so3_right_jacobian_inv",
]


def _small(dtype: torch.dtype) -> float:
    """The angle below which the series expansions are used (their truncation error is far below eps there)."""
    return 1e-4 if dtype == torch.float64 else 1e-2


def _check_last(x: Tensor, n: int, name: str) -> None:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.shape[-1:] != (n,):
        raise ValueError(f"{name} must have shape (..., {n}), got {tuple(x.shape)}")


# Quaternions [qx, qy, qz, qw]
def quat_normalize(q: Tensor, positive_w: bool = True) -> Tensor:
    """Unit quaternion ``(..., 4)``, sign chosen so that ``qw >= 0`` (kept as given when not ``positive_w``)."""
    _check_last(q, 4, "q")
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(q.dtype).tiny)
    return torch.where(q[..., 3:4] < 0, -q, q) if positive_w else q


def quat_conj(q: Tensor) -> Tensor:
    """Conjugate (= inverse for unit quaternions) ``(..., 4)``."""
    return torch.cat([-q[..., :3], q[..., 3:]], dim=-1)


def quat_mul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a * b`` of quaternions ``(..., 4)`` in ``[x, y, z, w]`` order."""
    av, aw = a[..., :3], a[..., 3:]
    bv, bw = b[..., :3], b[..., 3:]
    av_b, bv_b = (av, bv) if av.shape == bv.shape else torch.broadcast_tensors(av, bv)
    v = aw * bv + bw * av + torch.cross(av_b, bv_b, dim=-1)
    w = aw * bw - (av * bv).sum(-1, keepdim=True)
    return torch.cat([v, w], dim=-1)


def quat_rotate(q: Tensor, v: Tensor) -> Tensor:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``."""
    qv, qw = q[..., :3], q[..., 3:]
    if qv.shape != v.shape:  # broadcast only when needed (it costs more than the rotation)
        qv, v = torch.broadcast_tensors(qv, v)
        qw = qw.expand(qv.shape[:-1] + (1,))
    t = 2.0 * torch.cross(qv, v, dim=-1)
    return v + qw * t + torch.cross(qv, t, dim=-1)


def _rotmat_entries(x, y, z, w) -> list:
    """The nine entries (row-major) of the rotation matrix of the unit quaternion ``[x, y, z, w]``, from
    tensors or Python floats alike."""
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return [
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    ]


def quat_to_rotmat(q: Tensor) -> Tensor:
    """Rotation matrices ``(..., 3, 3)`` from unit quaternions ``(..., 4)`` (``[x, y, z, w]``); one float64
    quaternion without gradient through Python floats (the same bits, many times faster)."""
    _check_last(q, 4, "q")
    if q.shape == (4,) and q.dtype == torch.float64 and not q.requires_grad:
        return torch.tensor(_rotmat_entries(*q.tolist()), dtype=q.dtype, device=q.device).view(3, 3)
    return torch.stack(_rotmat_entries(*q.unbind(-1)), dim=-1).reshape(q.shape[:-1] + (3, 3))


def quat_angle(q: Tensor) -> Tensor:
    """Rotation angles in radians ``(...)``, in ``[0, pi]``, of quaternions ``(..., 4)`` ``[x, y, z, w]`` of any
    norm: ``2 atan2(|v|, |w|)``, accurate for tiny and for large angles."""
    return 2.0 * torch.atan2(q[..., :3].norm(dim=-1), q[..., 3].abs())


def rotmat_to_quat(R: Tensor) -> Tensor:
    """Unit quaternions ``(..., 4)`` (``[x, y, z, w]``, ``w >= 0``) from rotation matrices ``(..., 3, 3)``
    (Shepperd's method, branch-free: of four equal formulas the one with the largest denominator)."""
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {tuple(R.shape)}")
    m = R.reshape(R.shape[:-2] + (9,))
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m.unbind(-1)
    q_abs = torch.sqrt(torch.stack([
        1.0 + m00 + m11 + m22,
        1.0 + m00 - m11 - m22,
        1.0 - m00 + m11 - m22,
        1.0 - m00 - m11 + m22,
    ], dim=-1).clamp_min(0.0))
    # rows: candidates (w, x, y, z) * 4 * (component with the largest magnitude)
    cand = torch.stack([
        torch.stack([q_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], dim=-1),
        torch.stack([m21 - m12, q_abs[..., 1] ** 2, m10 + m01, m02 + m20], dim=-1),
        torch.stack([m02 - m20, m10 + m01, q_abs[..., 2] ** 2, m12 + m21], dim=-1),
        torch.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[..., 3] ** 2], dim=-1),
    ], dim=-2)
    cand = cand / (2.0 * q_abs[..., :, None].clamp_min(0.1))
    best = torch.nn.functional.one_hot(q_abs.argmax(dim=-1), 4).to(R.dtype)
    wxyz = (cand * best[..., :, None]).sum(dim=-2)
    return quat_normalize(torch.cat([wxyz[..., 1:], wxyz[..., :1]], dim=-1))


def rotmat_project(M: Tensor) -> Tensor:
    """The nearest rotation matrices ``(..., 3, 3)`` (Frobenius norm) to matrices ``M (..., 3, 3)``:
    ``U diag(1, 1, det(U V^T)) V^T`` of the SVD ``M = U S V^T`` (any ``M`` has one: callers check ``M``)."""
    if M.shape[-2:] != (3, 3):
        raise ValueError(f"M must have shape (..., 3, 3), got {tuple(M.shape)}")
    U, _, Vh = torch.linalg.svd(M)
    d = torch.sign(torch.det(U @ Vh))
    d = torch.where(d == 0, torch.ones_like(d), d)
    return (U * torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1)[..., None, :]) @ Vh


# SO(3)
def so3_hat(phi: Tensor) -> Tensor:
    """Skew-symmetric matrices ``(..., 3, 3)`` with ``hat(a) @ b = a x b``."""
    _check_last(phi, 3, "phi")
    x, y, z = phi.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(phi.shape[:-1] + (3, 3))


def _theta(phi: Tensor):
    """``(theta, theta^2, small)`` of vectors ``phi (..., 3)``, each ``(..., 1)``; ``theta`` is 1 where small."""
    theta2 = (phi * phi).sum(-1, keepdim=True)
    small = theta2 < _small(phi.dtype) ** 2
    # a safe value where the exact formula is not used, so its gradient stays finite
    theta = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    return theta, theta2, small


def so3_exp(phi: Tensor) -> Tensor:
    """Unit quaternions ``(..., 4)`` from rotation vectors ``(..., 3)``."""
    _check_last(phi, 3, "phi")
    theta, theta2, small = _theta(phi)
    half = 0.5 * theta
    k = torch.where(small, 0.5 - theta2 / 48.0 + theta2 * theta2 / 3840.0, torch.sin(half) / theta)
    w = torch.where(small, 1.0 - theta2 / 8.0 + theta2 * theta2 / 384.0, torch.cos(half))
    return torch.cat([k * phi, w], dim=-1)


def so3_log(q: Tensor) -> Tensor:
    """Rotation vectors ``(..., 3)`` (angle in ``[0, pi]``) from unit quaternions ``(..., 4)``."""
    _check_last(q, 4, "q")
    q = torch.where(q[..., 3:4] < 0, -q, q)  # shortest rotation
    v, w = q[..., :3], q[..., 3:]
    n, n2, small = _theta(v)
    w_safe = torch.where(small, w, torch.ones_like(w))
    # near the identity: 2 atan(n / w) / n = (2 / w) (1 - n^2 / (3 w^2) + ...)
    k_small = 2.0 / w_safe * (1.0 - n2 / (3.0 * w_safe * w_safe))
    k = torch.where(small, k_small, 2.0 * torch.atan2(n, w) / n)
    return k * v


def so3_left_jacobian(phi: Tensor) -> Tensor:
    """Left Jacobian ``J_l(phi)`` of SO(3), ``(..., 3, 3)``; ``se3_exp`` uses it as ``V``."""
    theta, theta2, small = (x[..., None] for x in _theta(phi))
    ts2 = theta * theta  # safe (1 where small) for the exact branch
    # (1 - cos t) / t^2 written as 2 sin^2(t/2) / t^2: no cancellation just above the series threshold
    a = torch.where(small, 0.5 - theta2 / 24.0, 2.0 * torch.sin(0.5 * theta) ** 2 / ts2)
    b = torch.where(small, 1.0 / 6.0 - theta2 / 120.0, (theta - torch.sin(theta)) / (ts2 * theta))
    W = so3_hat(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand_as(W)
    return eye + a * W + b * (W @ W)


def so3_left_jacobian_inv(phi: Tensor) -> Tensor:
    """Inverse of the left Jacobian of SO(3), ``(..., 3, 3)``."""
    theta, theta2, small = (x[..., None] for x in _theta(phi))
    half = 0.5 * theta
    c = torch.where(small, 1.0 / 12.0 + theta2 / 720.0,
                    (1.0 - half * torch.cos(half) / torch.sin(half)) / (theta * theta))
    W = so3_hat(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand_as(W)
    return eye - 0.5 * W + c * (W @ W)


def so3_right_jacobian_inv(phi: Tensor) -> Tensor:
    """Inverse of the right Jacobian of SO(3), ``(..., 3, 3)``: ``log(exp(phi) exp(d)) ~= phi + J_r^-1 d``."""
    return so3_left_jacobian_inv(-phi)


# SE(3) on (..., 7) = [t, q_xyzw]
def se3_identity(*shape: int, dtype=None, device=None) -> Tensor:
    """Identity poses ``(*shape, 7)``."""
    p = torch.zeros(*shape, 7, dtype=dtype, device=device)
    p[..., 6] = 1.0
    return p


def se3_normalize(pose: Tensor, positive_w: bool = True) -> Tensor:
    """Re-normalise the quaternion part (``qw >= 0``, or its sign kept when not ``positive_w``) of poses
    ``(..., 7)``."""
    _check_last(pose, 7, "pose")
    return torch.cat([pose[..., :3], quat_normalize(pose[..., 3:], positive_w)], dim=-1)


def se3_exp(xi: Tensor) -> Tensor:
    """Poses ``(..., 7)`` from tangent vectors ``xi = [rho, phi] (..., 6)``."""
    _check_last(xi, 6, "xi")
    rho, phi = xi[..., :3], xi[..., 3:]
    t = (so3_left_jacobian(phi) @ rho[..., None])[..., 0]
    return torch.cat([t, so3_exp(phi)], dim=-1)


def se3_log(pose: Tensor) -> Tensor:
    """Tangent vectors ``[rho, phi] (..., 6)`` from poses ``(..., 7)``."""
    _check_last(pose, 7, "pose")
    phi = so3_log(pose[..., 3:])
    rho = (so3_left_jacobian_inv(phi) @ pose[..., :3, None])[..., 0]
    return torch.cat([rho, phi], dim=-1)


def se3_inv(pose: Tensor) -> Tensor:
    """Inverse poses ``(..., 7)``."""
    _check_last(pose, 7, "pose")
    qi = quat_conj(pose[..., 3:])
    return torch.cat([-quat_rotate(qi, pose[..., :3]), qi], dim=-1)


def se3_compose(a: Tensor, b: Tensor) -> Tensor:
    """Composition ``a * b`` of poses ``(..., 7)`` (broadcasting)."""
    _check_last(a, 7, "a")
    _check_last(b, 7, "b")
    t = a[..., :3] + quat_rotate(a[..., 3:], b[..., :3])
    q = quat_mul(a[..., 3:], b[..., 3:])
    return torch.cat([t, q], dim=-1)


def se3_between(a: Tensor, b: Tensor) -> Tensor:
    """Relative pose ``a^-1 * b`` (``b`` expressed in the frame of ``a``), ``(..., 7)``."""
    return se3_compose(se3_inv(a), b)


def se3_act(pose: Tensor, points: Tensor) -> Tensor:
    """Transform points: ``R p + t``; ``pose (..., 7)`` broadcasts with ``points (..., 3)`` (a cloud
    ``(N, 3)`` takes ``pose[None]``)."""
    _check_last(pose, 7, "pose")
    _check_last(points, 3, "points")
    return quat_rotate(pose[..., 3:], points) + pose[..., :3]


def _upper_blocks(a: Tensor, b: Tensor, d: Tensor) -> Tensor:
    """The ``(..., 6, 6)`` block matrices ``[[a, b], [0, d]]`` of ``(..., 3, 3)`` blocks."""
    return torch.cat([torch.cat([a, b], dim=-1), torch.cat([torch.zeros_like(a), d], dim=-1)], dim=-2)


def se3_adjoint(pose: Tensor) -> Tensor:
    """Adjoint matrices ``(..., 6, 6)`` for the ``[rho, phi]`` order: ``[[R, [t]x R], [0, R]]``, so that
    ``X * exp(xi) = exp(Ad(X) xi) * X``."""
    _check_last(pose, 7, "pose")
    R = quat_to_rotmat(pose[..., 3:])
    return _upper_blocks(R, so3_hat(pose[..., :3]) @ R, R)


def se3_ad(xi: Tensor) -> Tensor:
    """Small adjoint ``ad(xi) = [[hat(phi), hat(rho)], [0, hat(phi)]] (..., 6, 6)`` of ``xi (..., 6)``: ``ad(a) b``
    is the Lie bracket ``[a, b]``."""
    _check_last(xi, 6, "xi")
    P = so3_hat(xi[..., 3:])
    return _upper_blocks(P, so3_hat(xi[..., :3]), P)


def _se3_q_parts(xi: Tensor):
    """Barfoot's ``Q(rho, phi)`` (the top-right block of the left Jacobian of SE(3)) split into its part
    odd in ``xi`` (a skew matrix ``hat(v)``) and its even part, so that ``Q(xi) = hat(v) + E`` and
    ``Q(-xi) = -hat(v) + E``. Returns ``(v (..., 3), E (..., 3, 3))``.

    The nine matrix products of Barfoot's formula reduce, with ``[a]x [b]x = b a^T - (a . b) I``,
    ``s = phi . rho`` and ``t^2 = phi . phi``, to
    ``v = (1/2 - c2 t^2) rho + (2 c2 - c1) s phi`` and
    ``E = c1 (rho phi^T + phi rho^T) - 2 c3 s phi phi^T + 2 s (c3 t^2 - c1) I``.
    """
    rho, phi = xi[..., :3], xi[..., 3:]
    theta2 = (phi * phi).sum(-1, keepdim=True)
    # below this angle the series (exact to round-off there) keeps the precision and the backward pass finite
    small = theta2 < (1e-2 if phi.dtype == torch.float64 else 1e-1) ** 2
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2)
    sn, cs = torch.sin(t), torch.cos(t)
    th4 = theta2 * theta2
    c1 = torch.where(small, 1.0 / 6.0 - theta2 / 120.0 + th4 / 5040.0, (t - sn) / (t2 * t))
    # (t^2 + 2 cos t - 2) as (t^2 - 4 sin^2(t/2)): the absolute error stays ~eps t^2, not eps
    c2 = torch.where(small, 1.0 / 24.0 - theta2 / 720.0 + th4 / 40320.0,
                     (t2 - 4.0 * torch.sin(0.5 * t) ** 2) / (2.0 * t2 * t2))
    c3 = torch.where(small, 1.0 / 120.0 - theta2 / 2520.0 + th4 / 120960.0,
                     (2.0 * t - 3.0 * sn + t * cs) / (2.0 * t2 * t2 * t))
    s = (phi * rho).sum(-1, keepdim=True)
    v = (0.5 - c2 * theta2) * rho + (2.0 * c2 - c1) * s * phi
    outer = rho[..., :, None] * phi[..., None, :]
    E = (c1[..., None] * (outer + outer.transpose(-1, -2))
         - (2.0 * c3 * s)[..., None] * (phi[..., :, None] * phi[..., None, :]))
    diag = (2.0 * s * (c3 * theta2 - c1))
    E = E + diag[..., None] * torch.eye(3, dtype=xi.dtype, device=xi.device)
    return v, E


def se3_left_jacobian_inv(xi: Tensor) -> Tensor:
    """Inverse left Jacobian of SE(3), ``(..., 6, 6)``: ``[[J_l^-1, -J_l^-1 Q J_l^-1], [0, J_l^-1]]``."""
    _check_last(xi, 6, "xi")
    Ji = so3_left_jacobian_inv(xi[..., 3:])
    v, E = _se3_q_parts(xi)
    Q = so3_hat(v) + E
    return _upper_blocks(Ji, -(Ji @ Q @ Ji), Ji)


def se3_right_jacobian_inv(xi: Tensor) -> Tensor:
    """Inverse right Jacobian of SE(3), ``(..., 6, 6)``: ``log(exp(xi) exp(d)) ~= xi + J_r^-1(xi) d``."""
    return se3_left_jacobian_inv(-xi)


def se3_to_matrix(pose: Tensor) -> Tensor:
    """Homogeneous matrices ``(..., 4, 4)`` from poses ``(..., 7)``."""
    _check_last(pose, 7, "pose")
    R = quat_to_rotmat(pose[..., 3:])
    top = torch.cat([R, pose[..., :3, None]], dim=-1)
    bottom = torch.zeros(pose.shape[:-1] + (1, 4), dtype=pose.dtype, device=pose.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def se3_from_matrix(T: Tensor) -> Tensor:
    """Poses ``(..., 7)`` from homogeneous ``(..., 4, 4)`` or ``(..., 3, 4)`` matrices."""
    if T.shape[-2:] not in ((4, 4), (3, 4)):
        raise ValueError(f"T must have shape (..., 4, 4) or (..., 3, 4), got {tuple(T.shape)}")
    return torch.cat([T[..., :3, 3], rotmat_to_quat(T[..., :3, :3])], dim=-1)


def se3_to_kornia(pose: Tensor):
    """A :class:`kornia.geometry.liegroup.Se3` (batch shape ``(...)``) from poses ``(..., 7)`` ``[t, q_xyzw]``.

    Kornia's quaternions are scalar-first; its tangent vectors are ``[rho, phi]`` as here, so ``log``, ``exp``,
    composition, inversion and ``adjoint`` agree. Differentiable.

    Example:
        >>> T = se3_to_kornia(se3_exp(torch.tensor([[0.1, 0.2, 0.3, 0.0, 0.0, 0.5]])))
        >>> T.r.q.data.shape, T.t.shape
        (torch.Size([1, 4]), torch.Size([1, 3]))
    """
    from kornia.geometry.liegroup import Se3
    from kornia.geometry.quaternion import Quaternion

    _check_last(pose, 7, "pose")
    return Se3(Quaternion(torch.cat([pose[..., 6:], pose[..., 3:6]], dim=-1)), pose[..., :3])


def se3_from_kornia(T) -> Tensor:
    """Poses ``(..., 7)`` ``[t, q_xyzw]`` from a :class:`kornia.geometry.liegroup.Se3` (the inverse of
    :func:`se3_to_kornia`; differentiable).

    Example:
        >>> pose = se3_exp(torch.tensor([[0.1, 0.2, 0.3, 0.0, 0.0, 0.5]]))
        >>> bool(torch.equal(se3_from_kornia(se3_to_kornia(pose)), pose))
        True
    """
    from kornia.geometry.liegroup import Se3

    if not isinstance(T, Se3):
        raise TypeError(f"T must be a kornia.geometry.liegroup.Se3, got {type(T).__name__}")
    q = T.r.q.data  # (..., 4) [w, x, y, z]
    return torch.cat([T.t, q[..., 1:], q[..., :1]], dim=-1)
