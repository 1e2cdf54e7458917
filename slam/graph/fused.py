"""The pose-graph maths in torch (closed forms, few torch calls): residuals, their Jacobians, normal-equation
blocks and the retraction, vectorised over edges, on any device, differentiable to second order at the identity.

Notation: ``D = z^-1 T_i^-1 T_j``, ``r = Log(D) = [rho, phi]``,
``J_j = J_r^-1(r)``, ``J_i = -J_l^-1(r) Ad(z^-1)``, ``Omega = L L^T`` (Cholesky, constant per call).
With the whitened rows ``[A_i, A_j, u] = L^T [J_i, J_j, r]`` the blocks of an edge are ``A_a^T A_b`` and
its gradient ``A_a^T u``: one product of a ``(2k+1, k)`` matrix with its transpose gives all of them.
"""
from __future__ import annotations

import math
from typing import Optional, Tuple

import numpy as np
import torch

from slam.lie import quat_to_rotmat, so3_hat

__all__ = ["bmm", "copy_", "error_poses", "normal_blocks", "r3so3_jacobians", "se3_adjoint_t", "se3_jacobians_t",
           "se3_residuals", "se3_retract"]

Tensor = torch.Tensor

# below this rotation angle the series of (1 - (t/2) cot(t/2)) / t^2 is used, as in slam.lie
_SMALL = {torch.float64: 1e-4, torch.float32: 1e-2}
_TAN2_HALF_SMALL = {dt: math.tan(a / 2.0) ** 2 for dt, a in _SMALL.items()}  # the same bound on |v|^2 / w^2
# below this angle the coefficients of Barfoot's Q take their series (_Q_SERIES)
_SMALL_Q = {torch.float64: 1e-2, torch.float32: 1e-1}


def _numpy_ok(*ts: Tensor) -> bool:
    return all(t.device.type == "cpu" and not t.requires_grad for t in ts)


def bmm(a: Tensor, b: Tensor, out: Optional[Tensor] = None) -> Tensor:
    """Batched matrix product ``a @ b`` (broadcasting), optionally written into ``out``; on the CPU without
    autograd numpy's ``matmul`` (several times faster than torch's for 6x6 float64 matrices)."""
    if _numpy_ok(a, b) and (out is None or _numpy_ok(out)):
        if out is None:
            return torch.from_numpy(np.matmul(a.numpy(), b.numpy()))
        np.matmul(a.numpy(), b.numpy(), out=out.numpy())
        return out
    if out is None:
        return torch.matmul(a, b)
    if a.requires_grad or b.requires_grad:  # out= arguments do not support autograd
        return out.copy_(torch.matmul(a, b))
    return torch.matmul(a, b, out=out)


def copy_(dst: Tensor, src: Tensor) -> Tensor:
    """``dst.copy_(src)`` through numpy on the CPU (a strided copy there is ~1.5x faster)."""
    if _numpy_ok(dst, src):
        np.copyto(dst.numpy(), src.numpy())
        return dst
    return dst.copy_(src)


def _dot(a: Tensor, b: Tensor) -> Tensor:
    """Row-wise dot products ``(E, 1)`` of ``(E, 3)`` vectors (torch's sum over a dimension of 3 took 3x)."""
    p = a * b
    return p[:, :1] + p[:, 1:2] + p[:, 2:]


def _qmul(a: Tensor, b: Tensor, conj_b: bool = False) -> Tensor:
    """Hamilton product ``a * b`` (or ``a * b^*``) of quaternions ``(E, 4)`` ``[x, y, z, w]``."""
    av, aw, bv, bw = a[:, :3], a[:, 3:], b[:, :3], b[:, 3:]
    if conj_b:  # b^* = (-bv, bw)
        v = bw * av - aw * bv - torch.linalg.cross(av, bv)
        w = aw * bw + _dot(av, bv)
    else:
        v = aw * bv + bw * av + torch.linalg.cross(av, bv)
        w = aw * bw - _dot(av, bv)
    return torch.cat([v, w], dim=-1)


def _rotate(q: Tensor, v: Tensor) -> Tensor:
    """Rotate ``v (E, 3)`` by unit quaternions ``q (E, 4)``."""
    qv = q[:, :3]
    t = torch.linalg.cross(qv, v)
    t = t + t
    return v + q[:, 3:] * t + torch.linalg.cross(qv, t)


def error_poses(poses: Tensor, ii: Tensor, jj: Tensor, zinv: Tensor) -> Tuple[Tensor, Tensor]:
    """Translation ``(E, 3)`` and quaternion ``(E, 4)`` of ``D = z^-1 T_i^-1 T_j`` for every edge.

    With ``a = q(z^-1) q_i^*``: ``t_D = t(z^-1) + R(a) (t_j - t_i)`` and ``q_D = a q_j``.

    Args:
        poses: ``(N, 7)`` poses.
        ii, jj: ``(E,)`` long, the first and second pose of each edge.
        zinv: ``(E, 7)`` inverted measurements.
    """
    Pi, Pj = poses[ii], poses[jj]
    a = _qmul(zinv[:, 3:], Pi[:, 3:], conj_b=True)
    return zinv[:, :3] + _rotate(a, Pj[:, :3] - Pi[:, :3]), _qmul(a, Pj[:, 3:])


def _log_terms(q: Tensor):
    """Rotation vector ``phi (E, 3)``, ``theta^2 (E, 1)`` and ``c = (1 - (t/2) cot(t/2)) / t^2 (E, 1)``
    (the coefficient of ``hat(phi)^2`` in ``J_l^-1(phi)``) from unit quaternions ``q (E, 4)``.

    With ``h = atan2(|v|, |w|)``: ``phi = 2 h v / |v|`` and ``(t/2) cot(t/2) = h |w| / |v|``. Below the angle
    ``_SMALL`` the series in ``x = |v|^2 / w^2``, smooth at the identity (where ``|v|`` has no derivative);
    each branch of a ``where`` is finite everywhere, so the unselected one passes no NaN to the gradients.
    """
    v, w = q[:, :3], q[:, 3:]
    n2 = _dot(v, v)
    # |w| without abs or atan2 (their second derivatives import torch._dynamo on first use: seconds)
    aw = torch.where(w < 0, -w, w)
    # angle 2 h below _SMALL, i.e. |v| / |w| = tan(h) below tan(_SMALL / 2)
    small = n2 < _TAN2_HALF_SMALL.get(q.dtype, 2.5e-5) * (w * w)
    n = torch.where(small, 1.0, n2).sqrt()
    # h = atan2(n, |w|) in [0, pi/2], through atan of a ratio <= 1
    big = n > aw
    h = torch.where(big, 0.5 * math.pi - torch.atan(aw / torch.where(big, n, 1.0)),
                    torch.atan(n / torch.where(big, 1.0, aw)))
    ws = torch.where(small, w, 1.0)  # |w| ~ 1 where small
    x = torch.where(small, n2, 0.0) / (ws * ws)
    series = 1.0 - x / 3.0  # atan(sqrt x) / sqrt x
    k = torch.where(small, 2.0 * series / ws, torch.where(w < 0, -2.0, 2.0) * h / n)
    theta2 = torch.where(small, 4.0 * x * series * series, 4.0 * h * h)
    c = torch.where(small, 1.0 / 12.0 + theta2 / 720.0, (1.0 - h * aw / n) / torch.where(small, 1.0, theta2))
    return k * v, theta2, c


def se3_residuals(poses: Tensor, ii: Tensor, jj: Tensor, zinv: Tensor, chart: str = "se3"):
    """Residuals ``r (E, 6)`` of every edge and the terms their Jacobians reuse.

    Args:
        poses: ``(N, 7)`` poses.
        ii, jj: ``(E,)`` long, the first and second pose of each edge.
        zinv: ``(E, 7)`` inverted measurements.
        chart: ``"se3"`` (``r = Log(D)``) or ``"r3so3"`` (``r = [t(D), Log_SO3(q(D))]``).

    Returns:
        ``r (E, 6)`` and ``aux = (theta^2 (E, 1), c (E, 1), t_D (E, 3), q_D (E, 4))`` for
        :func:`se3_jacobians_t` (``theta`` the rotation angle of ``D``, ``c`` as in :func:`_log_terms`).
    """
    t, q = error_poses(poses, ii, jj, zinv)
    phi, theta2, c = _log_terms(q)
    if chart == "se3":
        # rho = J_l^-1(phi) t = t - phi x t / 2 + c (phi (phi . t) - theta^2 t)
        pxt = torch.linalg.cross(phi, t)
        rho = t - 0.5 * pxt + c * (phi * _dot(phi, t) - theta2 * t)
    elif chart == "r3so3":
        rho = t
    else:
        raise ValueError(f"chart must be 'se3' or 'r3so3', got {chart!r}")
    return torch.cat([rho, phi], dim=-1), (theta2, c, t, q)


def se3_adjoint_t(pose: Tensor) -> Tensor:
    """Transposed adjoints ``Ad(T)^T (E, 6, 6)`` (``[[R^T, 0], [R^T [t]x^T, R^T]]``), contiguous."""
    q = pose[:, 3:]
    Rt = quat_to_rotmat(torch.cat([-q[:, :3], q[:, 3:]], dim=-1))  # R(q^*) = R^T, contiguous
    out = pose.new_zeros(pose.shape[0], 6, 6)
    out[:, :3, :3] = Rt
    out[:, 3:, 3:] = Rt
    out[:, 3:, :3] = bmm(Rt, so3_hat(pose[:, :3])).neg_()  # [t]x^T = -[t]x
    return out


_FLAT9 = {  # index / sign tables that write 3x3 matrices of vectors as flat (E, 9) rows
    "hat": [0, 2, 1, 2, 0, 0, 1, 0, 0],  # hat(a) = a[hat] * sign
    "sign": [0, -1, 1, 1, 0, -1, -1, 1, 0],
    "eye": [1, 0, 0, 0, 1, 0, 0, 0, 1],
}
_CONST: dict = {}


def _const(name: str, like: Tensor) -> Tensor:
    """The table ``name`` of :data:`_FLAT9` on the device of ``like`` (long, or ``like``'s dtype), cached."""
    floating = name in ("sign", "eye")
    key = (name, like.device, like.dtype if floating else torch.long)
    if key not in _CONST:
        _CONST[key] = torch.tensor(_FLAT9[name], dtype=key[2], device=like.device)
    return _CONST[key]


def _jl_inv_and_q(r: Tensor, theta2: Tensor, c: Tensor) -> Tuple[Tensor, Tensor]:
    """``A = J_l^-1(phi)`` and ``Q = -A Q_B(r) A`` ``(E, 3, 3)``, the blocks of the SE(3)
    ``J_l^-1(r) = [[A, Q], [0, A]]`` (``Q_B``: Barfoot's ``Q``, ``hat(v) + S`` with ``S`` symmetric).

    ``A = (1 - c t^2) I - hat(phi) / 2 + c phi phi^T``; ``theta2 (E, 1)`` and ``c (E, 1)`` come from the
    logarithm. The 3x3 matrices are built as flat ``(E, 9)`` rows.
    """
    E = r.shape[0]
    Hx, sg, eye = (_const(n, r) for n in ("hat", "sign", "eye"))
    rho, phi = r[:, :3], r[:, 3:]

    def rows(a):  # a[i] and a[j] of the flat entry (i, j)
        return a[:, :, None].expand(E, 3, 3).reshape(E, 9), a[:, None, :].expand(E, 3, 3).reshape(E, 9)

    phi_i, phi_j = rows(phi)
    rho_i, rho_j = rows(rho)
    pp = phi_i * phi_j  # phi phi^T
    A = torch.addcmul((1.0 - c * theta2) * eye, c, pp).sub_(0.5 * phi[:, Hx] * sg)
    # coefficients of Q_B: exact where the angle is not small, their series (to theta^4) below 1e-2
    small = theta2 < _SMALL_Q.get(r.dtype, 1e-1) ** 2
    t2 = torch.where(small, 1.0, theta2)
    t = t2.sqrt()
    sn, cs, sh = torch.sin(t), torch.cos(t), torch.sin(0.5 * t)
    t4 = t2 * t2
    exact = torch.cat([(t - sn) / (t2 * t), (t2 - 4.0 * sh * sh) / (2.0 * t4),
                       (2.0 * t - 3.0 * sn + t * cs) / (2.0 * t4 * t)], dim=-1)
    series = _Q_SERIES.to(r.dtype)
    series = series[0] + theta2 * (series[1] + theta2 * series[2])
    c1, c2, c3 = torch.where(small, series, exact).split(1, dim=-1)
    s = _dot(phi, rho)
    v = (0.5 - c2 * theta2) * rho + (2.0 * c2 - c1) * s * phi
    sym = rho_i * phi_j + phi_i * rho_j  # rho phi^T + phi rho^T
    M = c1 * sym - (2.0 * c3 * s) * pp + (2.0 * s * (c3 * theta2 - c1)) * eye + v[:, Hx] * sg
    A, M = A.view(E, 3, 3), M.view(E, 3, 3)
    return A, bmm(bmm(A, M), A).neg_()


# series coefficients of (c1, c2, c3) in powers (1, t^2, t^4), one column each
_Q_SERIES = torch.tensor([[1.0 / 6.0, 1.0 / 24.0, 1.0 / 120.0],
                          [-1.0 / 120.0, -1.0 / 720.0, -1.0 / 2520.0],
                          [1.0 / 5040.0, 1.0 / 40320.0, 1.0 / 120960.0]], dtype=torch.float64)


def se3_jacobians_t(r: Tensor, aux, neg_adz_t: Optional[Tensor], out: Optional[Tensor] = None,
                    poses: Optional[Tensor] = None, ii: Optional[Tensor] = None,
                    jj: Optional[Tensor] = None, ws: Optional[dict] = None) -> Tensor:
    """Transposed Jacobians and residual stacked as rows: ``[J_i^T; J_j^T; r^T]`` ``(E, 13, 6)``.

    Chart ``"se3"`` (``neg_adz_t = -Ad(z^-1)^T`` given): ``J_j^T = J_r^-1(r)^T = [[A, 0], [Q, A]]`` and
    ``J_i^T = -Ad(z^-1)^T J_l^-1(r)^T``, where ``J_l^-1(r)^T`` is ``J_j^T`` with each 3x3 block
    transposed (``J_l^-1(-r) = J_l^-1(r)`` with every block transposed; see :func:`_jl_inv_and_q`).
    Chart ``"r3so3"`` (``neg_adz_t = None``; ``poses, ii, jj`` needed): :func:`r3so3_jacobians`.

    Args:
        r: ``(E, 6)`` residuals from :func:`se3_residuals`.
        aux: its second output.
        neg_adz_t: ``(E, 6, 6)`` ``-Ad(z^-1)^T`` (constant per call), or None for ``"r3so3"``.
        out: optional ``(E, 13, 6)`` zero-initialised buffer, reused between calls (the entries that
            are zero stay zero).
        poses, ii, jj: ``(N, 7)``, ``(E,)``, ``(E,)`` for the ``"r3so3"`` chart only.
        ws: optional dict of scratch buffers reused between calls.

    Returns:
        ``(E, 13, 6)``.
    """
    E = r.shape[0]
    if out is None:
        out = r.new_zeros(E, 13, 6)
    if neg_adz_t is None:
        Ji, Jj = r3so3_jacobians(poses, ii, jj, aux[3], r)
        out[:, :6] = Ji.transpose(1, 2)
        out[:, 6:12] = Jj.transpose(1, 2)
        out[:, 12] = r
        return out
    A, Q = _jl_inv_and_q(r, aux[0], aux[1])
    out[:, 6:9, :3] = A
    out[:, 9:12, 3:] = A
    out[:, 9:12, :3] = Q
    out[:, 12] = r
    JlT = workspace_buffer(ws, "JlT", (E, 6, 6), r)  # J_j^T with every 3x3 block transposed
    copy_(JlT.view(E, 2, 3, 2, 3), out[:, 6:12].view(E, 2, 3, 2, 3).transpose(2, 4))
    bmm(neg_adz_t, JlT, out=out[:, :6])
    return out


def r3so3_jacobians(poses: Tensor, ii: Tensor, jj: Tensor, qD: Tensor, r: Tensor) -> Tuple[Tensor, Tensor]:
    """Jacobians ``J_i, J_j (E, 6, 6)`` of the ``"r3so3"`` residual ``r = [t(D), Log_SO3(q(D))]``.

    With ``C = blockdiag(R(D), J_r^-1(phi))`` (the derivative of ``r`` under a right perturbation of ``D``):
    ``J_j = C`` and ``J_i = -C Ad(T_j^-1 T_i)``.

    Args:
        poses: ``(N, 7)`` poses.
        ii, jj: ``(E,)`` edge ends.
        qD: ``(E, 4)`` the error poses' quaternions (from :func:`se3_residuals`).
        r: ``(E, 6)`` the residuals.
    """
    from slam.lie import se3_adjoint, se3_between, so3_right_jacobian_inv

    C = r.new_zeros(r.shape[0], 6, 6)
    C[:, :3, :3] = quat_to_rotmat(qD)
    C[:, 3:, 3:] = so3_right_jacobian_inv(r[:, 3:])
    return -(C @ se3_adjoint(se3_between(poses[jj], poses[ii]))), C


def se3_retract(poses: Tensor, xi: Tensor) -> Tensor:
    """``T exp(xi)`` for poses ``(N, 7)`` and tangent steps ``xi = [rho, phi] (N, 6)`` (right perturbation).

    ``exp(xi) = (J_l(phi) rho, [sin(t/2) phi / t, cos(t/2)])`` with
    ``J_l(phi) rho = rho + a phi x rho + b phi x (phi x rho)``; ``a, b`` take their series below ``_SMALL``
    (autograd through a step of zero stays exact, to second order).
    """
    rho, phi = xi[:, :3], xi[:, 3:]
    theta2 = _dot(phi, phi)
    small = theta2 < _SMALL.get(xi.dtype, 1e-2) ** 2
    t = torch.where(small, 1.0, theta2).sqrt()
    k = torch.where(small, 0.5 - theta2 / 48.0, torch.sin(0.5 * t) / t)  # sin(t/2) / t
    a = 2.0 * k * k
    b = torch.where(small, 1.0 / 6.0 - theta2 / 120.0, (t - torch.sin(t)) / (t * t * t))
    cos_half = torch.where(small, 1.0 - theta2 / 8.0, torch.cos(0.5 * t))
    pxr = torch.linalg.cross(phi, rho)
    te = rho + a * pxr + b * torch.linalg.cross(phi, pxr)
    qe = torch.cat([k * phi, cos_half], dim=-1)
    return torch.cat([poses[:, :3] + _rotate(poses[:, 3:], te), _qmul(poses[:, 3:], qe)], dim=-1)


def workspace_buffer(ws: Optional[dict], name: str, shape, like: Tensor) -> Tensor:
    """A contiguous tensor of ``shape`` in storage kept in the dict ``ws`` between calls (fresh when ``ws`` is
    None; a larger one kept there serves a smaller shape)."""
    if ws is None:
        return like.new_empty(shape)
    need = math.prod(shape)
    t = ws.get(name)
    if t is None or t.numel() < need or t.dtype != like.dtype or t.device != like.device:
        t = ws[name] = like.new_empty(need)
    return t[:need].view(shape)


def normal_blocks(JT: Tensor, L: Tensor, weights: Optional[Tensor] = None,
                  ws: Optional[dict] = None) -> Tuple[Tensor, Tensor]:
    """Per-edge blocks of ``J^T W Omega J`` and ``J^T W Omega r``.

    Args:
        JT: ``(E, 2k+1, k)`` rows ``[J_i^T; J_j^T; r^T]`` (``k`` unknowns per pose).
        L: ``(E, k, k)`` lower Cholesky factors of the information matrices (``Omega = L L^T``).
        weights: optional ``(E,)`` robust-kernel weights ``W``.
        ws: optional dict of buffers reused between calls (the outputs live there: they are
            overwritten by the next call with the same ``ws``).

    Returns:
        ``blocks (E, 4, k, k)`` (``ii, ij, ji, jj``) and ``g (E, 2, k)`` (``i, j``).
    """
    E, m, k = JT.shape
    AT = bmm(JT, L, out=workspace_buffer(ws, "AT", (E, m, k), JT))  # whitened rows [A_i^T; A_j^T; u^T]
    if weights is not None:
        AT.mul_(weights.sqrt()[:, None, None])
    # one product gives every block, the gradient and chi2: F = [A_i, A_j, u]^T [A_i, A_j, u]
    A = copy_(workspace_buffer(ws, "A", (E, k, m), JT), AT.transpose(1, 2))  # contiguous operands
    F = bmm(AT, A, out=workspace_buffer(ws, "F", (E, m, m), JT))
    blocks = copy_(workspace_buffer(ws, "blocks", (E, 2, 2, k, k), JT),
                   F[:, :2 * k, :2 * k].view(E, 2, k, 2, k).permute(0, 1, 3, 2, 4))
    g = F[:, :2 * k, 2 * k].reshape(E, 2, k)
    return blocks.view(E, 4, k, k), g
