"""The least-squares problem the optimiser's outer loop drives: evaluate the cost, linearise into ``(H, g)``,
solve the damped system, retract a step; what does not change during a call is made once.
"""
from __future__ import annotations

import threading
from typing import List, Optional

import torch

from slam.graph.config import OptimizerConfig
from slam.graph.costs import RobustKernel
from slam.graph.fused import (bmm, normal_blocks, se3_adjoint_t, se3_jacobians_t, se3_residuals, se3_retract,
                              workspace_buffer)
from slam.graph.linear import BlockPattern, LinearSolverError, assemble_blocks, build_pattern, make_solver
from slam.graph.pose_graph import PoseGraph, require_spd_information
from slam.lie import se3_compose, se3_inv, se3_log, se3_normalize, se3_right_jacobian_inv

__all__ = ["PLANAR_DIMS", "TorchProblem", "held_poses"]

Tensor = torch.Tensor

PLANAR_DIMS = (0, 1, 5)  # x, y, yaw in the [rho, phi] tangent order


def held_poses(cfg: OptimizerConfig, gauge: str, num_poses: int) -> List[int]:
    """Indices of the poses held constant: ``cfg.fixed`` (any sequence, array or tensor of ints), plus pose 0
    for the ``"first"`` gauge; a ``ValueError`` names an index out of range."""
    fixed = [int(f) for f in cfg.fixed] + ([0] if gauge == "first" else [])
    for f in fixed:
        if not 0 <= f < num_poses:
            raise ValueError(f"fixed pose index {f} is out of range [0, {num_poses})")
    return fixed


#: Most bytes of per-edge buffers kept for the next problem after an optimisation ends (parking-garage: 33 MB).
WORKSPACE_MAX_BYTES = 2 ** 28
_WORKSPACES: List[dict] = []  # at most one, taken by one problem at a time
_WORKSPACE_LOCK = threading.Lock()


class TorchProblem:
    """One optimisation's state in torch (float64 on the graph's device).

    Args:
        graph: the :class:`PoseGraph` (its tensors are detached: the optimisation itself is not
            differentiated; see :mod:`slam.graph.implicit` for the gradients of its result).
        cfg: the :class:`OptimizerConfig`.
        kernel: an optional robust kernel.
        gauge: ``"free"``, ``"first"`` or ``"prior"`` (as resolved by the optimiser: GN holds pose 0).
        solver: a linear solver name (see :func:`slam.graph.linear.make_solver`).
    """

    def __init__(self, graph: PoseGraph, cfg: OptimizerConfig, kernel: Optional[RobustKernel], gauge: str,
                 solver):
        dt = torch.float64
        # unit quaternions made exact; the sign is kept so that untouched poses come back as they went in
        self.poses = se3_normalize(graph.poses.detach().to(dt), positive_w=False)
        self.ii, self.jj = graph.ii, graph.jj
        self.meas = se3_normalize(graph.measurements.detach().to(dt), positive_w=False)
        self.zinv = se3_inv(self.meas)  # constant per call: inverted once
        self.chart = graph.chart
        # J_i^T = -Ad(z^-1)^T J_l^-1(r)^T: the constant factor made once (the "r3so3" chart has its own)
        self.neg_adz_t = se3_adjoint_t(self.zinv).neg_() if graph.chart == "se3" else None
        self.info = graph.information.detach().to(dt)
        # Omega = L L^T: whitens the Jacobians (J^T Omega J = (L^T J)^T (L^T J)) and gives chi2 = |L^T r|^2
        L, fail = torch.linalg.cholesky_ex(self.info)
        require_spd_information(self.info, graph.ii, graph.jj, fail, symmetry=cfg.check_information)
        self.L = L.contiguous()  # LAPACK's factors are column-major: row-major ones multiply faster
        self.kernel = kernel
        N, E = self.poses.shape[0], self.ii.shape[0]
        dev = self.poses.device
        planar = graph.is_planar() if cfg.planar is None else bool(cfg.planar)
        self.dims = torch.tensor(PLANAR_DIMS, device=dev) if planar else None
        self.k = 3 if planar else 6
        if self.dims is not None:
            d = self.dims
            self.rows = torch.cat([d, d + 6, torch.tensor([12], device=dev)])  # rows of [J_i^T; J_j^T; r^T]
            self.L_red = torch.linalg.cholesky(self.info[:, d][:, :, d]).contiguous()
        # the per-edge buffers of the linearisation (slam.graph.fused): an earlier problem's (pages already mapped)
        with _WORKSPACE_LOCK:
            self.ws = _WORKSPACES.pop() if _WORKSPACES else {}
        self.JT = workspace_buffer(self.ws, "JT", (E, 13, 6), self.meas).zero_()  # its structural zeros stay zero
        fixed = held_poses(cfg, gauge, N)
        free = torch.ones(N, dtype=torch.bool, device=dev)
        free[fixed] = False
        self.pattern: BlockPattern = build_pattern(self.ii, self.jj, free, self.k)
        k, n = self.k, self.pattern.num_vars
        self.H_buf = (workspace_buffer(self.ws, "H", (self.pattern.num_blocks + 1, k, k), self.meas),
                      workspace_buffer(self.ws, "g", (n + 1, k), self.meas))
        self.H_damped = workspace_buffer(self.ws, "H_damped", (self.pattern.nnz,), self.meas)  # H + lambda D
        self.all_free = not fixed
        if not self.all_free:
            self.free_idx = free.nonzero()[:, 0]
            self.free_var = self.pattern.var_index[self.free_idx]
        self.prior = None
        # "free": nothing held, unless the caller fixes poses (which then anchor the result)
        self.reanchor = gauge == "free" and not fixed
        if gauge == "prior" and bool(free[0]):
            self.prior = (self.poses[0].clone(), cfg.prior_weight, int(self.pattern.var_index[0]))
        self.lin = make_solver(solver, self.pattern.size)
        self.size = self.pattern.size
        self.damping = cfg.damping
        self._dscale: Optional[Tensor] = None

    def evaluate(self, poses: Tensor):
        """Cost, chi2 and ``(r, aux, w)`` (residuals, terms reused by the Jacobians, kernel weights)."""
        r, aux = se3_residuals(poses, self.ii, self.jj, self.zinv, self.chart)
        u = bmm(r[:, None, :], self.L)  # (E, 1, 6): (L^T r)^T
        s = u.square_().sum((1, 2))
        chi2 = float(s.sum())
        if self.kernel is None:
            cost, w = chi2, None
        else:
            rho, w = self.kernel(s)
            cost = float(rho.sum())
        if self.prior is not None:
            p0, wgt, _ = self.prior
            r0 = se3_log(se3_compose(se3_inv(p0), poses[0]))
            cost += wgt * float((r0 * r0).sum())
        return cost, chi2, (r, aux, w)

    def linearize(self, poses: Tensor, cache):
        """``(H (nnz,), g (n k,))``: the Gauss-Newton system ``J^T W Omega J``, ``J^T W Omega r`` at ``poses``."""
        r, aux, w = cache
        JT = se3_jacobians_t(r, aux, self.neg_adz_t, self.JT, poses, self.ii, self.jj, self.ws)
        L = self.L
        if self.dims is not None:
            JT, L = JT[:, self.rows][:, :, self.dims], self.L_red
        blocks, gb = normal_blocks(JT, L, w, self.ws)
        H, g = assemble_blocks(self.pattern, blocks, gb, self.H_buf)
        if self.prior is not None:
            p0, wgt, v0 = self.prior
            r0 = se3_log(se3_compose(se3_inv(p0), poses[0]))
            J0 = se3_right_jacobian_inv(r0)
            if self.dims is not None:
                J0, r0 = J0[self.dims][:, self.dims], r0[self.dims]
            k = self.k
            pos = int(self.pattern.diag_blocks[v0]) * k * k + torch.arange(k * k, device=H.device)
            H = H.index_add(0, pos, (wgt * J0.T @ J0).reshape(-1))
            g = g.index_add(0, torch.arange(v0 * k, v0 * k + k, device=g.device), wgt * J0.T @ r0)
        self._dscale = H[self.pattern.diag_pos].clamp(1e-6, 1e32) if self.damping == "diagonal" else None
        return H, g

    def solve(self, H: Tensor, g: Tensor, lam: float) -> Tensor:
        """``dx (n k,)`` solving ``(H + lambda D) dx = -g``; raises :class:`~slam.graph.linear.LinearSolverError`."""
        Hd = H
        if lam > 0:  # into a buffer kept for the call: H (megabytes) is copied at every trial
            Hd = self.H_damped.copy_(H)
            Hd.index_add_(0, self.pattern.diag_pos,
                          lam * self._dscale if self._dscale is not None else torch.full_like(g, lam))
        dx = self.lin.solve(self.pattern, Hd, -g)
        if not bool(torch.isfinite(dx).all()):
            raise LinearSolverError("the linear solve produced non-finite values (singular system)")
        return dx

    def predicted_decrease(self, dx: Tensor, g: Tensor, lam: float) -> float:
        """Decrease of the cost predicted by the damped quadratic model: ``dx^T (lambda D dx - g)``."""
        D = self._dscale if self._dscale is not None else 1.0
        return float(dx @ (lam * D * dx - g))

    def retract(self, poses: Tensor, dx: Tensor) -> Tensor:
        """``T exp(dx)`` for the free poses ``(N, 7)`` (the held ones unchanged)."""
        xi = dx.view(-1, self.k)
        if self.dims is not None:
            xi = xi.new_zeros(xi.shape[0], 6).index_copy_(1, self.dims, xi)
        if self.all_free:  # variable v is pose v
            return se3_retract(poses, xi)
        out = poses.clone()
        out[self.free_idx] = se3_retract(poses[self.free_idx], xi[self.free_var])
        return out

    def finish(self, x: Tensor, moved: bool) -> Tensor:
        """The result; with the free gauge (and ``moved``) moved rigidly so that pose 0 is back at its
        initial value (the costs are invariant to a common rigid motion)."""
        if self.reanchor and moved:
            x0 = self.poses[0]
            x = se3_compose(se3_compose(x0, se3_inv(x[0]))[None], x)
            x[0] = x0
        return x

    def release(self) -> None:
        """Hand the per-edge buffers to the next problem (this one no longer linearises)."""
        size = sum(t.numel() * t.element_size() for t in self.ws.values())
        with _WORKSPACE_LOCK:
            if size <= WORKSPACE_MAX_BYTES and not _WORKSPACES:
                _WORKSPACES.append(self.ws)
        self.ws = None
