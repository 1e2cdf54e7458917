"""The accelerator's per-edge maths in numpy and in C: :class:`HostProblem`, a
:class:`~slam.graph.problem.PoseGraphProblem` on numpy arrays (CPU only).

Why a numpy twin of the torch reference (:mod:`slam.graph.fused`): on the CPU the work of one
Levenberg-Marquardt iteration is ~150 array calls whatever the graph's size, and a torch eager call costs
1.2-2 us of dispatch against 0.3-1 us for numpy. On a 9-pose graph that dispatch *is* the run time (torch:
5 ms for the 4 iterations GTSAM does in 0.5 ms); on large graphs both run the same vectorised loops over the
edges. The math is that of :mod:`slam.graph.fused` (same notation, same closed forms, same series below the
same angles); the tests check that both give the same residuals, Jacobians, normal equations and iterates
to round-off against the torch reference.

What makes the call count small: every bilinear product of the geometry (quaternion products, rotating a
vector by a quaternion, cross products) is one outer product and one matrix product with a constant
table of the product's coefficients (``a (x) b @ C``: 2 calls instead of ~10 column-by-column ones, and a
BLAS product on large graphs). The tables are derived at import from the torch reference functions
(:func:`slam.graph.fused._qmul`, :func:`slam.lie.quat_to_rotmat`, :func:`torch.linalg.cross`), not typed
in.

The C kernels (``slam.graph.accel._kernels``, from ``_kernels.c``; optional, built by ``setup.py`` where a C
compiler is found, chosen by ``OptimizerConfig.backend = "auto"`` or ``"c"``): the same math again, edge by
edge in one call per step: residuals with their chi2, the Jacobian products ``F`` of every edge, the
retraction, the measurement terms of the setup, the dense assembly and the re-anchoring. On a 9-pose graph
the numpy functions spend ~1 ms of call overhead where GTSAM needs 0.4 ms in all; the C kernels bring the
whole optimisation to ~0.3 ms (5x), and the benchmark files 1.1-1.65x (no per-edge temporaries; the sparse
Cholesky they share dominates there). The numpy functions are the fallback where the kernels were not
built (``backend="numpy"`` runs no compiled code at all).

Assembly (a scatter-add of the per-edge products into ``H`` and ``g``) goes through torch's
``index_add_`` on views of the same memory: numpy has no fast scatter-add (``np.add.at`` and
``np.add.reduceat`` measured 20x and 10x slower over rows of 36 values). Small systems are dense and
solved by LAPACK directly (see :class:`HostProblem`).

Example:
    >>> import numpy as np
    >>> q = np.array([[0.0, 0.0, np.sin(0.25), np.cos(0.25)]])  # 0.5 rad about z
    >>> v = np.array([[1.0, 0.0, 0.0]])
    >>> rotate(q, v).round(6)
    array([[0.877583, 0.479426, 0.      ]])
"""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np
import torch

from slam.graph import fused
from slam.graph.accel import _compiled
from slam.graph.cholesky import NotPositiveDefiniteError
from slam.graph.config import OptimizerConfig
from slam.graph.costs import RobustKernel
from slam.graph.linear import LinearSolverError, SparseCholeskySolver, build_pattern, make_solver
from slam.graph.pose_graph import PoseGraph, planar_arrays
from slam.graph.problem import SYMMETRY_RTOL, held_poses, information_factor, is_symmetric, unit_quaternions

__all__ = ["HostProblem", "cross", "host_kernels", "host_problem", "qmul", "qmul_conj",
           "rotate", "rotmat"]

# the float64 thresholds and series of slam.graph.fused: below _SMALL the series of the logarithm's terms,
# below _SMALL_Q those of the coefficients of Q (rows: powers 1, t^2, t^4; columns c1, c2, c3)
_SMALL, _SMALL_Q = fused._SMALL[torch.float64], fused._SMALL_Q[torch.float64]
_Q_SERIES = fused._Q_SERIES.numpy()
_TINY = np.finfo(np.float64).tiny
# edges linearised per chunk (bounds the per-edge buffers of large graphs; one chunk up to this size)
_CHUNK = 16384



def host_kernels():
    """The optional C kernels (``slam.graph.accel._kernels``, from ``_kernels.c``, built by setup.py where a C
    compiler is found): the same per-edge math in one call per step, with the constants above (set by
    :mod:`slam.graph.accel._compiled`). None when not built: the numpy functions below do the same work."""
    return _compiled.kernels


# -- bilinear tables ----------------------------------------------------------------------------------
def _outer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise outer products ``(E, n)``, ``(E, m)`` -> ``(E, n m)`` (entry ``i m + j`` = ``a_i b_j``)."""
    return (a[:, :, None] * b[:, None, :]).reshape(a.shape[0], -1)


def _bilinear_table(f, n: int, m: int) -> np.ndarray:
    """``C (n m, p)`` with ``f(a, b) = outer(a, b) @ C`` for a bilinear ``f`` (torch, batched)."""
    ea, eb = torch.eye(n, dtype=torch.float64), torch.eye(m, dtype=torch.float64)
    return f(ea.repeat_interleave(m, 0), eb.repeat(n, 1)).numpy().copy()


def _quadratic_table(f, n: int) -> np.ndarray:
    """``C (n n, p)``, symmetric in its two factors, with ``f(q) = outer(q, q) @ C`` for a homogeneous
    quadratic ``f`` (polarisation: ``C_ij = (f(e_i + e_j) - f(e_i) - f(e_j)) / 2``)."""
    e = torch.eye(n, dtype=torch.float64)
    fe = f(e)
    C = torch.empty(n, n, fe.shape[-1], dtype=torch.float64)
    for i in range(n):
        for j in range(n):
            C[i, j] = fe[i] if i == j else (f((e[i] + e[j])[None])[0] - fe[i] - fe[j]) / 2
    return C.reshape(n * n, -1).numpy().copy()


def _tables():
    from slam.lie import quat_to_rotmat, so3_hat

    def rot_h(q):  # homogeneous form |q|^2 R(q / |q|) of the rotation matrix, flat (9,)
        n2 = (q * q).sum(-1, keepdim=True)
        return n2 * quat_to_rotmat(q / n2.sqrt()).reshape(-1, 9)

    tables = {
        "qmul": _bilinear_table(fused._qmul, 4, 4),
        "qmul_conj": _bilinear_table(lambda a, b: fused._qmul(a, b, conj_b=True), 4, 4),
        "cross": _bilinear_table(lambda a, b: torch.linalg.cross(a, b), 3, 3),
        "rmat": _quadratic_table(rot_h, 4),  # (16, 9)
        "hat": so3_hat(torch.eye(3, dtype=torch.float64)).reshape(3, 9).numpy().copy(),  # hat(phi) = phi @ C
    }
    # the tables hold small integers and halves: snap away the round-off of their derivation
    return {k: np.round(v * 2.0) / 2.0 for k, v in tables.items()}


_T = _tables()
_EYE9 = np.eye(3).reshape(9)


def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products ``a b`` of quaternions ``(E, 4)`` ``[x, y, z, w]``."""
    return _outer(a, b) @ _T["qmul"]


def qmul_conj(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a b^*`` for quaternions ``(E, 4)``."""
    return _outer(a, b) @ _T["qmul_conj"]


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``R(q) v`` for unit quaternions ``(E, 4)`` and vectors ``(E, 3)`` (through the matrices: 1.2x faster
    than a trilinear table on 11 edges, 3.6x on 6275)."""
    return (rotmat(q) @ v[:, :, None])[:, :, 0]


def rotmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(E, 3, 3)`` of unit quaternions ``(E, 4)``."""
    return (_outer(q, q) @ _T["rmat"]).reshape(-1, 3, 3)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of ``(E, 3)`` vectors."""
    return _outer(a, b) @ _T["cross"]


# -- per-edge kernels (numpy versions of slam.graph.fused) --------------------------------------------
def _residuals(P: np.ndarray, ii: np.ndarray, jj: np.ndarray, zt: np.ndarray, zq: np.ndarray):
    """``r = Log(z^-1 T_i^-1 T_j)`` ``(E, 6)`` and ``(theta^2, c)`` ``(E,)`` for the Jacobians
    (:func:`slam.graph.fused.se3_residuals`)."""
    Pi, Pj = P[ii], P[jj]
    a = qmul_conj(zq, Pi[:, 3:])
    t = zt + rotate(a, Pj[:, :3] - Pi[:, :3])
    q = qmul(a, Pj[:, 3:])
    # logarithm of the rotation (fused._log_terms)
    v, w = q[:, :3], q[:, 3]
    n = np.sqrt((v * v).sum(1))
    aw = np.abs(w)
    h = np.arctan2(n, aw)
    theta2 = 4.0 * h * h
    ns = np.maximum(n, _TINY)
    phi = (np.copysign(2.0, w) * h / ns)[:, None] * v  # (sign chosen so that the angle is <= pi)
    small = theta2 < _SMALL * _SMALL
    c = np.where(small, 1.0 / 12.0 + theta2 / 720.0, (1.0 - h * aw / ns) / np.where(small, 1.0, theta2))
    # rho = J_l^-1(phi) t = t - phi x t / 2 + c (phi (phi . t) - theta^2 t)
    rho = t - 0.5 * cross(phi, t) + c[:, None] * (phi * (phi * t).sum(1)[:, None] - theta2[:, None] * t)
    return np.concatenate([rho, phi], axis=1), theta2, c


def _q_coefficients(theta2: np.ndarray):
    """``(c1, c2, c3)`` of Barfoot's ``Q`` (:func:`slam.graph.fused._jl_inv_and_q`), their series
    to ``theta^4`` below ``_SMALL_Q``."""
    small = theta2 < _SMALL_Q * _SMALL_Q
    t2 = np.where(small, 1.0, theta2)
    t = np.sqrt(t2)
    sn, sh = np.sin(t), np.sin(0.5 * t)
    t3 = t2 * t
    s0, s1, s2 = _Q_SERIES
    series = s0 + theta2[:, None] * (s1 + theta2[:, None] * s2)  # (E, 3)
    c1 = np.where(small, series[:, 0], (t - sn) / t3)
    c2 = np.where(small, series[:, 1], (t2 - 4.0 * sh * sh) / (2.0 * t2 * t2))
    c3 = np.where(small, series[:, 2], (2.0 * t - 3.0 * sn + t * np.cos(t)) / (2.0 * t3 * t2))
    return c1, c2, c3


def _jacobians_t(r: np.ndarray, theta2: np.ndarray, c: np.ndarray, neg_adz_t: np.ndarray,
                 out: np.ndarray) -> np.ndarray:
    """Rows ``[J_i^T; J_j^T; r^T]`` ``(E, 13, 6)`` into ``out`` (zero where they are zero), as
    :func:`slam.graph.fused.se3_jacobians_t` for the ``"se3"`` chart."""
    E = r.shape[0]
    rho, phi = r[:, :3], r[:, 3:]
    pp = _outer(phi, phi)
    # A = J_l^-1(phi) = (1 - c t^2) I - hat(phi) / 2 + c phi phi^T, flat (E, 9)
    A = (1.0 - c * theta2)[:, None] * _EYE9 + c[:, None] * pp - 0.5 * (phi @ _T["hat"])
    c1, c2, c3 = _q_coefficients(theta2)
    s = (phi * rho).sum(1)
    v = (0.5 - c2 * theta2)[:, None] * rho + ((2.0 * c2 - c1) * s)[:, None] * phi
    M = (c1[:, None] * (_outer(rho, phi) + _outer(phi, rho)) - (2.0 * c3 * s)[:, None] * pp
         + (2.0 * s * (c3 * theta2 - c1))[:, None] * _EYE9 + v @ _T["hat"])
    A, M = A.reshape(E, 3, 3), M.reshape(E, 3, 3)
    out[:, 6:9, :3] = A
    out[:, 9:12, 3:] = A
    np.negative(A @ M @ A, out=out[:, 9:12, :3])
    out[:, 12] = r
    # J_i^T = -Ad(z^-1)^T J_l^-1(r)^T, J_l^-1(r)^T = J_j^T with each 3x3 block transposed
    JlT = out[:, 6:12].reshape(E, 2, 3, 2, 3).transpose(0, 1, 4, 3, 2).reshape(E, 6, 6)
    np.matmul(neg_adz_t, JlT, out=out[:, :6])
    return out


def retract(P: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """``T exp(xi)`` for poses ``(N, 7)`` and steps ``[rho, phi] (N, 6)`` (:func:`slam.graph.fused.se3_retract`)."""
    rho, phi = xi[:, :3], xi[:, 3:]
    theta2 = (phi * phi).sum(1)
    t = np.maximum(np.sqrt(theta2), _TINY ** 0.25)
    sh = np.sin(0.5 * t)
    k = sh / t
    a = 2.0 * k * k
    b = np.where(theta2 < _SMALL * _SMALL, 1.0 / 6.0 - theta2 / 120.0, (t - np.sin(t)) / (t * t * t))
    pxr = cross(phi, rho)
    te = rho + a[:, None] * pxr + b[:, None] * cross(phi, pxr)
    qe = np.concatenate([k[:, None] * phi, np.cos(0.5 * t)[:, None]], axis=1)
    return np.concatenate([P[:, :3] + rotate(P[:, 3:], te), qmul(P[:, 3:], qe)], axis=1)


_LAPACK: list = []


def _lapack_cholesky():
    """LAPACK's ``dpotrf`` and ``dpotrs``, imported on first use (``scipy.linalg`` takes ~0.4 s to import, and
    a ``from ... import`` inside a function ~0.1 ms per call through scipy's lazy module loading)."""
    if not _LAPACK:
        from scipy.linalg import lapack

        _LAPACK.extend([lapack.dpotrf, lapack.dpotrs])
    return _LAPACK[0], _LAPACK[1]


# -- the problem the LM loop of slam.graph.optimizer drives -------------------------------------------
class HostProblem:
    """Per-call state of an optimisation on the CPU in numpy: :class:`~slam.graph.problem.PoseGraphProblem`
    as :class:`~slam.graph.problem.TorchProblem` implements it, with numpy arrays in place of tensors.

    Up to ``dense_max`` unknowns (and no explicit solver) the normal equations are dense: every entry
    of each edge's ``[J_i, J_j, r]^T W Omega [J_i, J_j, r]`` goes straight to its place in ``H`` or ``g``
    in one scatter-add and LAPACK's ``potrf``/``potrs`` solve them (no block pattern, no symbolic
    analysis: the setup of a 9-pose graph is ~20 calls). Above, ``H`` is block-sparse
    (:class:`~slam.graph.linear.BlockPattern`) and solved by the supernodal
    :class:`~slam.graph.cholesky.SymbolicCholesky`, or by ``solver``.

    Args:
        poses: ``(N, 7)`` float64 initial poses (unit quaternions).
        ii, jj: ``(E,)`` int64 edge ends.
        meas: ``(E, 7)`` float64 measurements.
        info: ``(E, 6, 6)`` float64 information matrices.
        L: ``(E, 6, 6)`` their lower Cholesky factors.
        free: ``(N,)`` bool, the poses optimised.
        planar: solve only ``(x, y, yaw)`` (see :class:`~slam.graph.optimizer.OptimizerConfig`).
        kernel: an optional robust kernel (called on torch views of the squared norms).
        solver: ``None`` for the built-in solves, or a :class:`~slam.graph.linear.LinearSolver` (called on
            torch views of the block-sparse system).
        damping: ``"identity"`` or ``"diagonal"``.
        reanchor: move the result rigidly so that pose 0 keeps its initial value (the free gauge).
        dense_max: the most unknowns solved densely.
        compiled: do the per-edge work (residuals, Jacobians and their products, retraction, the setup of
            the measurements, the dense assembly, the re-anchoring) in the C kernels ``slam.graph.accel._kernels``
            (one call each instead of ~10-60 numpy calls; a ``RuntimeError`` when they were not built).
    """

    def __init__(self, poses: np.ndarray, ii: np.ndarray, jj: np.ndarray, meas: np.ndarray, info: np.ndarray,
                 L: np.ndarray, free: np.ndarray, planar: bool = False, kernel=None, solver=None,
                 damping: str = "identity", reanchor: bool = False, dense_max: int = 400,
                 compiled: bool = False):
        C = host_kernels()
        if compiled and C is None:
            raise RuntimeError("the C kernels slam.graph.accel._kernels were not built (install attnloop where a C "
                               "compiler is found); use compiled=False")
        self._c = C if compiled else None
        if self._c is not None:  # the C kernels take C-contiguous int64 / float64 buffers
            ii, jj = np.ascontiguousarray(ii, dtype=np.int64), np.ascontiguousarray(jj, dtype=np.int64)
            poses, meas, L = (np.ascontiguousarray(a, dtype=np.float64) for a in (poses, meas, L))
        self.poses = poses
        self.ii, self.jj = ii, jj
        E = ii.shape[0]
        if self._c is not None:
            self.zt, self.zq, self.neg_adz_t = np.empty((E, 3)), np.empty((E, 4)), np.empty((E, 6, 6))
            self._c.measurement_terms(meas, self.zt, self.zq, self.neg_adz_t)
        else:
            mq = meas[:, 3:]
            Rt = rotmat(mq)  # R(z) = R(z^-1)^T
            self.zq = mq * np.array([-1.0, -1.0, -1.0, 1.0])  # z^-1 = (-R(z)^T t, q^*)
            self.zt = -(meas[:, None, :3] @ Rt)[:, 0]
            # -Ad(z^-1)^T = [[-R^T, 0], [R^T hat(t), -R^T]] with R = R(z^-1), t = t(z^-1)
            self.neg_adz_t = np.zeros((E, 6, 6))
            self.neg_adz_t[:, :3, :3] = -Rt
            self.neg_adz_t[:, 3:, 3:] = -Rt
            self.neg_adz_t[:, 3:, :3] = Rt @ (self.zt @ _T["hat"]).reshape(E, 3, 3)
        self.L = L
        # int64 index arrays throughout (the C kernels take no other; numpy < 2 on Windows defaults to int32)
        self.dims = np.array([0, 1, 5], dtype=np.int64) if planar else None  # x, y, yaw in the [rho, phi] order
        self.k = k = 3 if planar else 6
        if planar:
            d = self.dims
            self.rows = np.concatenate([d, d + 6, [12]]).astype(np.int64)  # rows of [J_i^T; J_j^T; r^T]
            self.L_red = np.linalg.cholesky(info[:, d][:, :, d])
        # the C kernel's selections of rows of [J_i^T; J_j^T; r^T] and of columns (all of them in 6-DoF)
        self._rows_c = self.rows if planar else np.arange(13, dtype=np.int64)
        self._dims_c = self.dims if planar else np.arange(6, dtype=np.int64)
        self.kernel, self.solver, self.damping, self.reanchor = kernel, solver, damping, reanchor
        # per-iteration products in buffers made once: fresh megabyte arrays pay their page faults at every
        # iteration (parking-garage: linearisation 13.8 -> 7.3 ms). Large graphs are linearised in chunks of
        # edges so that these buffers stay small (~4.4 kB per edge: 280 MB on a 65000-edge graph otherwise).
        C = min(E, _CHUNK)
        rows = 2 * k + 1
        self._F = np.empty((C, rows, rows))
        if self._c is None:
            self.JT = np.zeros((C, 13, 6))
            self._AT, self._A = np.empty((C, rows, k)), np.empty((C, k, rows))
        var = np.where(free, np.cumsum(free, dtype=np.int64) - 1, -1)
        self.all_free = bool(free.all())
        if not self.all_free:
            self.free_idx = np.flatnonzero(free)
        n = int(free.sum())
        self.size = m = n * k
        self.dense = solver is None and m <= dense_max
        if self.dense:
            self.diag_pos = np.arange(m) * (m + 1)
            self._potrf, self._potrs = _lapack_cholesky()
        if self.dense and self._c is not None:
            # H (m*m), then g (m): the C kernel adds each edge's entries to their places (var: -1 = fixed)
            self._var = var
            self.buf = np.empty(m * m + m)
        elif self.dense:
            # flat positions of each edge's (2k+1)^2 entries: H (m*m), then g (m), then a dump entry
            # (the residual row, and the rows / columns of fixed poses)
            p = np.arange(2 * k)
            v = np.stack([var[ii], var[jj]], 1)[:, p // k]  # (E, 2k) variable of each row
            ok = v >= 0
            glob = v * k + p % k
            dump = m * m + m
            idx = np.full((E, 2 * k + 1, 2 * k + 1), dump)
            idx[:, :2 * k, :2 * k] = np.where(ok[:, :, None] & ok[:, None, :], glob[:, :, None] * m + glob[:, None, :],
                                              dump)
            idx[:, :2 * k, 2 * k] = np.where(ok, m * m + glob, dump)
            self._idx = torch.from_numpy(idx.reshape(-1))
            self.buf = np.empty(dump + 1)
            self._buf_t = torch.from_numpy(self.buf)
        else:
            self.pattern = pattern = build_pattern(torch.from_numpy(ii), torch.from_numpy(jj),
                                                   torch.from_numpy(free), k)
            nb = pattern.num_blocks
            # assembly buffers (torch views of them: its index_add_ is the fastest scatter-add on the CPU,
            # 10x np.add.reduceat and 20x np.add.at over rows of 36 values)
            self.H_buf = np.empty((nb + 1, k * k))
            self.g_buf = np.empty((n + 1, k))
            self._H_t, self._g_t = torch.from_numpy(self.H_buf), torch.from_numpy(self.g_buf)
            self._eb, self._ev = pattern.edge_blocks.reshape(-1), pattern.edge_vars.reshape(-1)
            self._blocks, self._gb = np.empty((C, 2, 2, k, k)), np.empty((C, 2, k))
            self.diag_pos = ((pattern.diag_blocks.numpy() * (k * k))[:, None] + np.arange(k) * (k + 1)).reshape(-1)
            if solver is None:
                self.symbolic = SparseCholeskySolver().symbolic(pattern)
        self._dscale = None

    # -- costs -----------------------------------------------------------------------------------
    def evaluate(self, P: np.ndarray):
        """Cost, chi2 and ``(r, theta^2, c, w)`` at poses ``P (N, 7)``."""
        if self._c is not None:
            E = self.ii.shape[0]
            r, theta2, c, s = np.empty((E, 6)), np.empty(E), np.empty(E), np.empty(E)
            chi2 = self._c.residuals(P, self.ii, self.jj, self.zt, self.zq, self.L, r, theta2, c, s)
        else:
            r, theta2, c = _residuals(P, self.ii, self.jj, self.zt, self.zq)
            u = (r[:, None, :] @ self.L)[:, 0]  # (L^T r)^T
            s = (u * u).sum(1)
            chi2 = float(s.sum())
        if self.kernel is None:
            return chi2, chi2, (r, theta2, c, None)
        rho, w = self.kernel(torch.from_numpy(s))
        return float(rho.sum()), chi2, (r, theta2, c, w.numpy())

    def linearize(self, P: np.ndarray, cache) -> Tuple[np.ndarray, np.ndarray]:
        """``H = J^T W Omega J`` (dense ``(m m,)`` or block-major ``(nb k k,)``) and ``g = J^T W Omega r``
        ``(m,)``."""
        r, theta2, c, w = cache
        E = r.shape[0]
        if self.dense:
            self.buf.fill(0.0)
        else:
            self._H_t.zero_()
            self._g_t.zero_()
        for e0 in range(0, E, _CHUNK):
            self._linearize_edges(slice(e0, min(E, e0 + _CHUNK)), r, theta2, c, w)
        if self.dense:
            m = self.size
            H, g = self.buf[:m * m], self.buf[m * m:m * m + m]
        else:
            H, g = self.H_buf[:-1].reshape(-1), self.g_buf[:-1].reshape(-1)
        self._dscale = np.clip(H[self.diag_pos], 1e-6, 1e32) if self.damping == "diagonal" else None
        return H, g

    def _linearize_edges(self, sl: slice, r, theta2, c, w) -> None:
        """Add the edges ``sl``'s blocks of ``H`` and ``g`` (see :meth:`linearize`)."""
        n, k = sl.stop - sl.start, self.k
        L = self.L[sl] if self.dims is None else self.L_red[sl]
        if self._c is not None:
            F = self._F[:n]
            self._c.linearize(r[sl], theta2[sl], c[sl], self.neg_adz_t[sl], L, None if w is None else w[sl],
                              self._rows_c, self._dims_c, F)
        else:
            JT = _jacobians_t(r[sl], theta2[sl], c[sl], self.neg_adz_t[sl], self.JT[:n])
            if self.dims is not None:
                JT = JT[:, self.rows][:, :, self.dims]
            AT = np.matmul(JT, L, out=self._AT[:n])  # whitened rows [A_i^T; A_j^T; u^T]
            if w is not None:
                AT *= np.sqrt(w[sl])[:, None, None]
            # every block, the gradient and chi2 at once (a contiguous transpose: numpy's fast matmul loop)
            A = self._A[:n]
            np.copyto(A, AT.transpose(0, 2, 1))
            F = np.matmul(AT, A, out=self._F[:n])
        if self.dense and self._c is not None:
            m = self.size
            self._c.assemble_dense(F, self.ii[sl], self.jj[sl], self._var, self.buf[:m * m], self.buf[m * m:])
        elif self.dense:
            q = (2 * k + 1) ** 2
            self._buf_t.index_add_(0, self._idx[sl.start * q:sl.stop * q], torch.from_numpy(F.reshape(-1)))
        else:
            blocks, gb = self._blocks[:n], self._gb[:n]
            np.copyto(blocks, F[:, :2 * k, :2 * k].reshape(n, 2, k, 2, k).transpose(0, 1, 3, 2, 4))
            np.copyto(gb, F[:, :2 * k, 2 * k].reshape(n, 2, k))
            self._H_t.index_add_(0, self._eb[4 * sl.start:4 * sl.stop], torch.from_numpy(blocks.reshape(n * 4, k * k)))
            self._g_t.index_add_(0, self._ev[2 * sl.start:2 * sl.stop], torch.from_numpy(gb.reshape(n * 2, k)))

    def solve(self, H: np.ndarray, g: np.ndarray, lam: float) -> np.ndarray:
        """``dx (m,)`` solving ``(H + lambda D) dx = -g``; raises ``LinearSolverError``."""
        Hd = H.copy()
        if lam > 0:
            Hd[self.diag_pos] += lam * self._dscale if self._dscale is not None else lam
        if self.dense:
            m = self.size
            # H is symmetric: its C-ordered buffer is the Fortran-ordered matrix LAPACK wants (no copy)
            fac, info = self._potrf(Hd.reshape(m, m).T, lower=1, clean=0, overwrite_a=1)
            if info != 0:
                raise LinearSolverError("dense Cholesky failed: the matrix is not positive definite "
                                        f"(leading minor {info})")
            dx, _ = self._potrs(fac, -g, lower=1)
        elif self.solver is None:
            try:
                # backend "numpy" keeps the Cholesky off the C kernels too: what runs without the build
                dx = self.symbolic.factor(Hd, compiled=self._c is not None).solve(-g)
            except NotPositiveDefiniteError as exc:
                raise LinearSolverError(str(exc)) from None
        else:
            dx = self.solver.solve(self.pattern, torch.from_numpy(Hd), torch.from_numpy(-g)).numpy()
        if not np.isfinite(dx).all():
            raise LinearSolverError("the linear solve produced non-finite values (singular system)")
        return dx

    def predicted_decrease(self, dx: np.ndarray, g: np.ndarray, lam: float) -> float:
        """Decrease of the cost predicted by the damped quadratic model: ``dx^T (lambda D dx - g)``."""
        D = self._dscale if self._dscale is not None else 1.0
        return float(dx @ (lam * D * dx - g))

    def retract(self, P: np.ndarray, dx: np.ndarray) -> np.ndarray:
        xi = dx.reshape(-1, self.k)
        if self.dims is not None:
            full = np.zeros((xi.shape[0], 6))
            full[:, self.dims] = xi
            xi = full
        step = retract if self._c is None else self._retract_c
        if self.all_free:  # variable v is pose v
            return step(P, xi)
        out = P.copy()
        out[self.free_idx] = step(P[self.free_idx], xi)
        return out

    def _retract_c(self, P: np.ndarray, xi: np.ndarray) -> np.ndarray:
        out = np.empty_like(P)
        self._c.retract(P, np.ascontiguousarray(xi), out)
        return out

    def finish(self, P: np.ndarray, moved: bool) -> torch.Tensor:
        """The result ``(N, 7)`` as a tensor; with ``reanchor`` (and ``moved``), moved rigidly so that pose 0
        is back at its initial value: ``T <- T0_init T0^-1 T`` (the costs are invariant to it)."""
        if self.reanchor and moved and self._c is not None:
            out = np.empty_like(P)
            self._c.relocate(P, self.poses[0], out)
            P = out
        elif self.reanchor and moved:
            cq = qmul_conj(self.poses[:1, 3:], P[:1, 3:])  # rotation of T0_init T0^-1
            RT = rotmat(cq)[0].T
            ct = self.poses[:1, :3] - P[:1, :3] @ RT
            # as matrices acting on rows: t -> t R^T, q -> q M (rows cq e_j: left product by cq)
            M = qmul(np.repeat(cq, 4, 0), np.eye(4))
            P = np.concatenate([ct + P[:, :3] @ RT, P[:, 3:] @ M], axis=1)
            P[0] = self.poses[0]
        if not np.isfinite(P).all():  # the LM loop only accepts finite costs: a NaN here is a bug
            raise FloatingPointError("the optimised poses have a non-finite value")
        return torch.from_numpy(P)

    def weights(self, cache) -> Optional[torch.Tensor]:
        return None if cache[3] is None else torch.from_numpy(cache[3])


def host_problem(graph: PoseGraph, cfg: OptimizerConfig, kernel: Optional[RobustKernel], gauge: str, solver,
                  compiled: bool = False):
    """The :class:`HostProblem` of a CPU graph (its setup in numpy: ~30 calls), with the C kernels when
    ``compiled``; the arguments of :class:`~slam.graph.problem.TorchProblem`."""
    dt = torch.float64
    P0, meas0, info = (t.detach().to(dt).numpy() for t in (graph.poses, graph.measurements, graph.information))
    C = host_kernels() if compiled else None
    L = None
    if C is not None:  # the same steps as below in 3 calls (the setup is half of a 9-pose graph's time)
        P0, meas0, info = np.ascontiguousarray(P0), np.ascontiguousarray(meas0), np.ascontiguousarray(info)
        P, meas, L = np.empty_like(P0), np.empty_like(meas0), np.empty_like(info)
        C.unit_poses(P0, P)
        C.unit_poses(meas0, meas)
        if C.information_factors(info, L, cfg.check_information, SYMMETRY_RTOL) >= 0:
            L = None  # the torch factor below names the bad edge
    else:
        # unit quaternions (validated to 1e-3) made exact, as on the torch path
        P, meas = unit_quaternions(P0), unit_quaternions(meas0)
        # numpy's batched Cholesky first (~8 us on 11 edges against ~35 us for the torch factor, measured
        # ~0.1 ms per call in sequence); the torch factor names the first bad edge when it fails
        if not cfg.check_information or is_symmetric(info):
            try:
                L = np.linalg.cholesky(info)
            except np.linalg.LinAlgError:
                pass
    if L is None or C is None and not np.isfinite(L).all():
        L = information_factor(graph, torch.from_numpy(info), cfg.check_information).numpy()
    planar = planar_arrays(P0, meas0, info) if cfg.planar is None else bool(cfg.planar)
    fixed = held_poses(cfg, gauge, graph.num_poses)
    free = np.ones(graph.num_poses, dtype=bool)
    free[fixed] = False
    k = 3 if planar else 6
    lin = None if solver is None or isinstance(solver, str) and solver.lower() == "auto" else \
        make_solver(solver, int(free.sum()) * k)  # None: HostProblem's own (dense up to dense_max unknowns)
    return HostProblem(P, graph.ii.numpy(), graph.jj.numpy(), meas, info, L, free, planar, kernel, lin,
                       cfg.damping, reanchor=gauge == "free" and not fixed,
                       dense_max=400 if cfg.dense_max is None else cfg.dense_max, compiled=compiled)
