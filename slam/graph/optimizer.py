"""Gauss-Newton and Levenberg-Marquardt for pose graphs over sparse normal equations.

Each iteration linearises every edge at once (the closed forms of :mod:`slam.graph.fused`, checked
against :mod:`slam.graph.costs`), scatters the per-edge blocks into a fixed sparse pattern
(:mod:`slam.graph.linear`), solves ``(H + lambda D) dx = -g`` and retracts ``T <- T exp(dx)`` (right
perturbation). Everything that does not change during a call is made once: the pattern and the
symbolic Cholesky analysis, the inverted measurements and ``Ad(z^-1)``, the Cholesky factors of the
information matrices, and the buffers the per-iteration work writes into.

Backends: on the CPU (``OptimizerConfig.backend = "auto"``) the per-edge work runs in numpy
(:mod:`slam.graph.host`, the same closed forms with ~3x less call overhead; tiny graphs are solved
densely with LAPACK), elsewhere in torch (:mod:`slam.graph.fused`); both take the same steps up to
round-off (tested).

Gauge (a pose graph is invariant to moving all poses rigidly): ``"free"`` (default for LM) leaves the
gauge to the LM damping, as GTSAM does without a prior: the damped step is then the smallest of the
equally good Gauss-Newton steps, which from an odometry guess converges in fewer iterations than holding
pose 0 (parking-garage: 4 instead of 6, the same costs per iteration as GTSAM); the result is then moved
rigidly so that pose 0 keeps its initial value. ``"first"`` holds pose 0 constant (its unknowns are
removed; GN always does this), ``"prior"`` adds a strong prior on pose 0. Poses listed in ``fixed`` are
held constant too (and then anchor the result themselves).

Costs: ``chi2 = sum_e r_e^T Omega_e r_e`` (GTSAM's ``graph.error`` is ``0.5 * chi2``); with a robust
kernel the optimiser minimises ``sum_e rho(s_e)`` (reported as ``robust_cost``), ``chi2`` is still the
plain sum. For a planar graph (z = roll = pitch = 0 everywhere, as read from a 2D g2o file) the
problem splits exactly into (x, y, yaw) and (z, roll, pitch) parts with a zero gradient in the latter,
so only the 3-DoF part is solved (a 4x smaller system, identical result).

Example:
    >>> import torch
    >>> from slam.lie import se3_exp
    >>> from slam.graph.pose_graph import PoseGraph
    >>> step = se3_exp(torch.tensor([1.0, 0, 0, 0, 0, 0.5], dtype=torch.float64))
    >>> g = PoseGraph.from_lists([se3_exp(0.1 * torch.ones(6, dtype=torch.float64))] * 3,
    ...                          [(0, 1, step), (1, 2, step), (0, 2, se3_exp(torch.tensor(
    ...                              [1.0 + 0.97, 0.48, 0, 0, 0, 1.0], dtype=torch.float64)))])
    >>> res = optimize(g, method="lm")
    >>> res.status, res.graph.poses.shape, res.chi2 < res.initial_chi2
    (<Status.CONVERGED: 'converged'>, torch.Size([3, 7]), True)
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from enum import Enum
from typing import Dict, List, Optional, Tuple, Union

import numpy as np
import torch

from slam.graph.cholesky import limit_blas_threads
from slam.graph.costs import RobustKernel, make_kernel
from slam.graph.fused import bmm, normal_blocks, se3_adjoint_t, se3_jacobians_t, se3_residuals, se3_retract
from slam.graph.host import HostProblem, compiled_kernels, host_kernels
from slam.graph.initialization import initialize
from slam.graph.linear import (
    BlockPattern,
    LinearSolver,
    LinearSolverError,
    assemble_blocks,
    build_pattern,
    make_solver,
    scipy_available,
)
from slam.graph.pose_graph import PoseGraph, planar_arrays
from slam.lie import se3_compose, se3_inv, se3_log, se3_right_jacobian_inv

__all__ = ["OptimizationResult", "OptimizerConfig", "PoseGraphOptimizer", "Status", "optimize"]

Tensor = torch.Tensor

_PLANAR_DIMS = [0, 1, 5]  # x, y, yaw in the [rho, phi] tangent order


class Status(str, Enum):
    """Why the optimiser stopped (a ``str``, so ``result.status == "converged"`` works)."""

    CONVERGED = "converged"  # a stopping rule on the cost decrease (or the cost itself) was met
    MAX_ITERATIONS = "max_iterations"  # the iteration cap was reached first
    LAMBDA_LIMIT = "lambda_limit"  # LM: no damping up to lambda_max decreased the cost (minimum reached)
    DIVERGED = "diverged"  # GN: a step increased the cost; the best poses are returned
    SOLVER_FAILED = "solver_failed"  # the linear system could not be solved (e.g. unconstrained poses in GN)

    def __str__(self) -> str:  # print as the plain word
        return self.value


@dataclass
class OptimizerConfig:
    """Settings of :func:`optimize` (all thresholds in chi2 units, i.e. 2x GTSAM's error)."""

    max_iterations: int = 100  # outer iterations (accepted or GN steps); GTSAM's default is 100
    rel_tol: float = 1e-5  # converged when (cost - new_cost) < rel_tol * cost  (GTSAM relativeErrorTol)
    abs_tol: float = 2e-5  # converged when cost - new_cost < abs_tol  (GTSAM absoluteErrorTol 1e-5 x 2)
    cost_tol: float = 0.0  # converged when the cost falls to this value
    lambda_init: float = 1e-5  # initial LM damping (GTSAM's default)
    lambda_factor: float = 10.0  # lambda /= factor after a good step, *= factor after a bad one
    lambda_min: float = 1e-12  # lower clamp of lambda
    lambda_max: float = 1e10  # LM gives up (status lambda_limit) beyond this damping
    damping: str = "identity"  # "identity": H + lambda I (GTSAM's default); "diagonal": H + lambda diag(H)
    # how lambda moves (LM only): "gtsam" (/= lambda_factor after a good step, *= after a bad one: GTSAM's
    # default);
    # "nielsen" (the gain-ratio rule of g2o and Ceres: after a good step with gain ratio rho = actual /
    # predicted decrease, lambda *= max(1/3, 1 - (2 rho - 1)^3); after a bad one *= nu, nu doubling)
    lambda_update: str = "gtsam"
    # "free": LM damping, then re-anchored on pose 0; "first": hold pose 0; "prior": a prior on pose 0
    gauge: str = "free"
    prior_weight: float = 1e8  # information of the "prior" gauge (rotation and translation alike)
    fixed: Tuple[int, ...] = ()  # further pose indices held constant (e.g. an already-optimised map)
    kernel_width: Optional[float] = None  # width of a kernel given by name (default sqrt(chi2_0.95(6)))
    planar: Optional[bool] = None  # solve only (x, y, yaw); None: auto-detect with PoseGraph.is_planar()
    check_information: bool = True  # check every information matrix is SPD before optimising
    # where the per-edge work runs: "auto" = for a graph on the CPU the C kernels of slam.graph.host when
    # they were built (setup.py; one call per step: ~5x faster than numpy on tinyGrid3D), else its numpy
    # functions (~3x less call overhead than torch, 10x faster on tiny graphs); torch (slam.graph.fused) on
    # other devices; or "c", "numpy", "torch" (the C and numpy paths have no "prior" gauge and no "r3so3"
    # chart: "auto" uses torch for those)
    backend: str = "auto"
    # solver "auto": a dense Cholesky up to this many unknowns (no symbolic analysis), the sparse one above.
    # None: the crossover of the backend measured by benchmarks/posegraph_backends.py on sphere2500
    # subgraphs: 400 on numpy (dense wins at 420 unknowns, loses at 480), 240 on torch (wins at 240, loses at 360)
    dense_max: Optional[int] = None
    # torch (and OpenBLAS) threads during the call (restored afterwards; None leaves them). The work is
    # many small batched ops: on a busy CPU torch's OpenMP pool slowed them 10-40x when it had more
    # threads than free cores, while one thread loses little on an idle machine.
    num_threads: Optional[int] = 1
    verbose: bool = False  # print one line per iteration


@dataclass
class OptimizationResult:
    """What :func:`optimize` returns.

    Attributes:
        graph: the optimised :class:`PoseGraph` (same edges, new poses ``(N, 7)``; input dtype/device).
        chi2: final ``sum r^T Omega r`` (GTSAM error = ``0.5 * chi2``), without the prior of the gauge.
        initial_chi2: the same at the initial poses.
        robust_cost: final ``sum rho(s)`` when a kernel was used, else ``None``.
        status: a :class:`Status`.
        iterations: outer iterations done (accepted LM steps / GN steps).
        cost_history: the optimised cost after each iteration, starting with the initial one
            (chi2, or the robust cost with a kernel, plus the prior of a ``"prior"`` gauge).
        lambda_history: LM damping used for each accepted step.
        time_history: seconds since the call started at which each entry of ``cost_history`` was known
            (setup included), e.g. to time when a given cost was first reached.
        timings: seconds spent in ``setup``, ``linearize`` (residuals, Jacobians, assembly), ``solve``,
            ``evaluate`` (costs of trial steps) and ``total``.
        weights: ``(E,)`` final kernel weights (all ones without a kernel): near 0 marks a rejected edge.
    """

    graph: PoseGraph
    chi2: float
    initial_chi2: float
    status: Status
    iterations: int
    robust_cost: Optional[float] = None
    cost_history: List[float] = field(default_factory=list)
    lambda_history: List[float] = field(default_factory=list)
    time_history: List[float] = field(default_factory=list)
    timings: Dict[str, float] = field(default_factory=dict)
    weights: Optional[Tensor] = None
    message: str = ""

    @property
    def error(self) -> float:
        """GTSAM's error convention: ``0.5 * chi2``."""
        return 0.5 * self.chi2

    @property
    def converged(self) -> bool:
        return self.status in (Status.CONVERGED, Status.LAMBDA_LIMIT)


class _Problem:
    """The per-call state: float64 copies of the graph's tensors, constant per-edge factors, the pattern
    and reused buffers."""

    def __init__(self, graph: PoseGraph, cfg: OptimizerConfig, kernel: Optional[RobustKernel], gauge: str,
                 solver):
        dt = torch.float64
        # unit quaternions (validated to 1e-3) made exact, in the poses and in the measurements; the sign
        # is kept so that untouched poses come back as they went in
        self.poses = _unit_quaternions(graph.poses.detach().to(dt))
        self.ii, self.jj = graph.ii, graph.jj
        self.meas = _unit_quaternions(graph.measurements.detach().to(dt))
        self.zinv = se3_inv(self.meas)  # constant per call: inverted once
        self.chart = graph.chart
        # J_i^T = -Ad(z^-1)^T J_l^-1(r)^T: the constant factor made once (the "r3so3" chart has its own)
        self.neg_adz_t = se3_adjoint_t(self.zinv).neg_() if graph.chart == "se3" else None
        self.info = graph.information.detach().to(dt)
        # Omega = L L^T: whitens the Jacobians (J^T Omega J = (L^T J)^T (L^T J)) and gives chi2 = |L^T r|^2
        self.L = _information_factor(graph, self.info, cfg.check_information)
        self.kernel = kernel
        N, E = self.poses.shape[0], self.ii.shape[0]
        dev = self.poses.device
        planar = graph.is_planar() if cfg.planar is None else bool(cfg.planar)
        self.dims = torch.tensor(_PLANAR_DIMS, device=dev) if planar else None
        self.k = 3 if planar else 6
        if self.dims is not None:
            d = self.dims
            self.rows = torch.cat([d, d + 6, torch.tensor([12], device=dev)])  # rows of [J_i^T; J_j^T; r^T]
            self.L_red = torch.linalg.cholesky(self.info[:, d][:, :, d]).contiguous()
        self.JT = torch.zeros(E, 13, 6, dtype=dt, device=dev)  # reused by every linearisation
        self.ws: dict = {}  # further per-edge buffers of the linearisation (slam.graph.fused)
        fixed = _held_poses(cfg, gauge, N)
        free = torch.ones(N, dtype=torch.bool, device=dev)
        free[fixed] = False
        self.pattern: BlockPattern = build_pattern(self.ii, self.jj, free, self.k)
        k, n = self.k, self.pattern.num_vars
        self.H_buf = (torch.empty(self.pattern.num_blocks + 1, k, k, dtype=dt, device=dev),
                      torch.empty(n + 1, k, dtype=dt, device=dev))
        self.H_damped = torch.empty(self.pattern.nnz, dtype=dt, device=dev)  # H + lambda D
        self.all_free = not fixed
        if not self.all_free:
            self.free_idx = free.nonzero()[:, 0]
            self.free_var = self.pattern.var_index[self.free_idx]
        self.prior = None
        # "free": nothing held, unless the caller fixes poses (which then anchor the result)
        self.reanchor = gauge == "free" and not fixed
        if gauge == "prior" and bool(free[0]):
            self.prior = (self.poses[0].clone(), cfg.prior_weight, int(self.pattern.var_index[0]))
        self.lin = make_solver(solver, self.pattern.size, 240 if cfg.dense_max is None else cfg.dense_max)
        self.size = self.pattern.size
        self.damping = cfg.damping
        self._dscale: Optional[Tensor] = None

    # -- costs ----------------------------------------------------------------------------------
    def evaluate(self, poses: Tensor):
        """Cost, chi2 and ``(r, aux, w)`` (residuals, terms reused by the Jacobians, kernel weights)."""
        r, aux = se3_residuals(poses, self.ii, self.jj, self.zinv, self.chart)
        u = bmm(r[:, None, :], self.L)  # (E, 1, 6): (L^T r)^T
        s = u.square_().sum((1, 2))
        if self.kernel is None:
            chi2 = cost = float(s.sum())
            w = None
        else:
            rho, w = self.kernel(s)
            cost, chi2 = float(rho.sum()), float(s.sum())
        if self.prior is not None:
            p0, wgt, _ = self.prior
            r0 = se3_log(se3_compose(se3_inv(p0), poses[0]))
            cost += wgt * float((r0 * r0).sum())
        return cost, chi2, (r, aux, w)

    def linearize(self, poses: Tensor, cache):
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
        """``dx`` solving ``(H + lambda D) dx = -g``; raises :class:`LinearSolverError`."""
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

    def finish(self, x: Tensor, moved: bool) -> Tensor:
        """The result; with the free gauge (and ``moved``) moved rigidly so that pose 0 is back at its
        initial value (the costs are invariant to a common rigid motion)."""
        if self.reanchor and moved:
            x0 = self.poses[0]
            x = se3_compose(se3_compose(x0, se3_inv(x[0]))[None], x)
            x[0] = x0
        if not bool(torch.isfinite(x).all()):  # the LM loop only accepts finite costs: a NaN here is a bug
            raise FloatingPointError("the optimised poses have a non-finite value")
        return x

    def weights(self, cache) -> Optional[Tensor]:
        return cache[2]

    def retract(self, poses: Tensor, dx: Tensor) -> Tensor:
        xi = dx.view(-1, self.k)
        if self.dims is not None:
            xi = xi.new_zeros(xi.shape[0], 6).index_copy_(1, self.dims, xi)
        if self.all_free:  # variable v is pose v
            return se3_retract(poses, xi)
        out = poses.clone()
        out[self.free_idx] = se3_retract(poses[self.free_idx], xi[self.free_var])
        return out


def _unit_quaternions(P):
    """``(..., 7)`` poses (tensor or array) with their quaternions scaled to unit norm (a copy)."""
    if isinstance(P, Tensor):
        return torch.cat([P[..., :3], P[..., 3:] / P[..., 3:].norm(dim=-1, keepdim=True)], dim=-1)
    P = P.copy()
    P[..., 3:] /= np.sqrt((P[..., 3:] ** 2).sum(-1, keepdims=True))
    return P


def _held_poses(cfg: OptimizerConfig, gauge: str, num_poses: int) -> List[int]:
    """Indices of the poses held constant: ``cfg.fixed`` (any sequence, array or tensor of ints), plus pose 0
    for the ``"first"`` gauge; a ``ValueError`` names an index out of range."""
    fixed = [int(f) for f in cfg.fixed] + ([0] if gauge == "first" else [])
    for f in fixed:
        if not 0 <= f < num_poses:
            raise ValueError(f"fixed pose index {f} is out of range [0, {num_poses})")
    return fixed


def _backend(graph: PoseGraph, cfg: OptimizerConfig, gauge: str) -> str:
    """``"torch"``, ``"c"`` or ``"numpy"`` (both :mod:`slam.graph.host`) for this call (see
    ``OptimizerConfig.backend``)."""
    if cfg.backend not in ("auto", "torch", "c", "numpy"):
        raise ValueError(f"backend must be 'auto', 'torch', 'c' or 'numpy', got {cfg.backend!r}")
    if cfg.backend == "c" and not compiled_kernels():
        raise ValueError("backend 'c' needs the C kernels slam.graph._kernels, which were not built (install "
                         "attnloop where a C compiler is found); use backend='numpy' or 'auto'")
    unsupported = [why for bad, why in ((graph.poses.device.type != "cpu", f"device {graph.poses.device}"),
                                        (graph.chart != "se3", f"chart {graph.chart!r}"),
                                        (gauge == "prior", "gauge 'prior'")) if bad]
    if cfg.backend in ("c", "numpy") and unsupported:
        raise ValueError(f"backend {cfg.backend!r} does not support {', '.join(unsupported)}; use backend='torch'")
    if cfg.backend == "torch" or unsupported:
        return "torch"
    return "numpy" if cfg.backend == "numpy" or not compiled_kernels() else "c"


def _host_problem(graph: PoseGraph, cfg: OptimizerConfig, kernel: Optional[RobustKernel], gauge: str, solver,
                  compiled: bool = False):
    """The :class:`slam.graph.host.HostProblem` of a CPU graph (its setup in numpy: ~30 calls), with the C
    kernels when ``compiled``."""
    dt = torch.float64
    P0, meas0, info = (t.detach().to(dt).numpy() for t in (graph.poses, graph.measurements, graph.information))
    C = host_kernels() if compiled else None
    L = None
    if C is not None:  # the same steps as below in 3 calls (the setup is half of a 9-pose graph's time)
        P0, meas0, info = np.ascontiguousarray(P0), np.ascontiguousarray(meas0), np.ascontiguousarray(info)
        P, meas, L = np.empty_like(P0), np.empty_like(meas0), np.empty_like(info)
        C.unit_poses(P0, P)
        C.unit_poses(meas0, meas)
        if C.information_factors(info, L, cfg.check_information, _SYMMETRY_RTOL) >= 0:
            L = None  # the torch factor below names the bad edge
    else:
        # unit quaternions (validated to 1e-3) made exact, as on the torch path
        P, meas = _unit_quaternions(P0), _unit_quaternions(meas0)
        # numpy's batched Cholesky first (~8 us on 11 edges against ~35 us for the torch factor, measured
        # ~0.1 ms per call in sequence); the torch factor names the first bad edge when it fails
        if not cfg.check_information or _symmetric(info):
            try:
                L = np.linalg.cholesky(info)
            except np.linalg.LinAlgError:
                pass
    if L is None or C is None and not np.isfinite(L).all():
        L = _information_factor(graph, torch.from_numpy(info), cfg.check_information).numpy()
    planar = planar_arrays(P0, meas0, info) if cfg.planar is None else bool(cfg.planar)
    fixed = _held_poses(cfg, gauge, graph.num_poses)
    free = np.ones(graph.num_poses, dtype=bool)
    free[fixed] = False
    k = 3 if planar else 6
    lin = None if solver is None or isinstance(solver, str) and solver.lower() == "auto" else \
        make_solver(solver, int(free.sum()) * k)  # None: HostProblem's own (dense up to dense_max unknowns)
    return HostProblem(P, graph.ii.numpy(), graph.jj.numpy(), meas, info, L, free, planar, kernel, lin,
                       cfg.damping, reanchor=gauge == "free" and not fixed,
                       dense_max=400 if cfg.dense_max is None else cfg.dense_max, compiled=compiled)


_SYMMETRY_RTOL = 1e-6  # an information matrix is symmetric when |A - A^T| <= this * its largest diagonal entry


def _symmetric(info) -> bool:
    """Every ``(6, 6)`` matrix of ``info (E, 6, 6)`` (numpy) symmetric (the rule of :func:`_information_factor`)."""
    if (info == info.transpose(0, 2, 1)).all():  # the usual case, exactly (g2o files store a triangle)
        return True
    scale = np.maximum(info.diagonal(0, 1, 2).max(1), np.finfo(np.float64).tiny)
    return bool((np.abs(info - info.transpose(0, 2, 1)).max((1, 2)) <= _SYMMETRY_RTOL * scale).all())


def _information_factor(graph: PoseGraph, info: Tensor, check: bool) -> Tensor:
    """Lower Cholesky factors ``(E, 6, 6)`` of the information matrices ``info (E, 6, 6)`` (float64);
    a ``ValueError`` names the first edge whose matrix is not symmetric positive definite (the symmetry
    is only checked when ``check``)."""
    L, fail = torch.linalg.cholesky_ex(info)
    bad = fail != 0
    if check:
        # the largest entry of an SPD matrix is on its diagonal (any other matrix fails the Cholesky)
        scale = info.diagonal(dim1=-2, dim2=-1).amax(-1).clamp_min(torch.finfo(info.dtype).tiny)
        bad = bad | ((info - info.transpose(-1, -2)).abs().amax(dim=(-2, -1)) > _SYMMETRY_RTOL * scale)
    if bool(bad.any()):
        k = int(bad.nonzero()[0, 0])
        raise ValueError(f"information[{k}] (edge {int(graph.ii[k])} -> {int(graph.jj[k])}) is not "
                         f"symmetric positive definite")
    return L.contiguous()  # LAPACK's factors are column-major: row-major ones multiply ~3x faster


def optimize(graph: PoseGraph, method: str = "lm", kernel: Union[None, str, RobustKernel] = None,
             solver: Union[None, str, LinearSolver] = "auto", config: Optional[OptimizerConfig] = None,
             initialization: str = "none", **overrides) -> OptimizationResult:
    """Optimise the poses of a pose graph.

    Args:
        graph: the :class:`PoseGraph`; its ``poses (N, 7)`` are the initial guess (they are not modified).
        method: ``"lm"`` (Levenberg-Marquardt) or ``"gn"`` (Gauss-Newton).
        kernel: ``None``, a name (``"huber"``, ``"cauchy"``, ``"tukey"``, ``"geman_mcclure"``) or a
            :class:`~slam.graph.costs.RobustKernel` object.
        solver: ``"auto"`` (sparse direct when scipy is importable), ``"sparse"``, ``"dense"``, ``"pcg"`` or a
            :class:`~slam.graph.linear.LinearSolver`.
        config: an :class:`OptimizerConfig`; keyword ``overrides`` replace its fields
            (e.g. ``optimize(g, max_iterations=10, gauge="prior")``).
        initialization: the initial guess: ``"none"`` (the graph's poses), ``"chordal"`` (rotations by
            chordal relaxation, then translations by least squares, as GTSAM's ``InitializePose3``) or
            ``"spanning_tree"`` (composed along a breadth-first tree of the edges); see
            :mod:`slam.graph.initialization`. ``initial_chi2`` is then the chi2 of that guess.

    Returns:
        An :class:`OptimizationResult` (``result.graph``, ``result.chi2``, ``result.status``,
        ``result.iterations``, ``result.cost_history``, ``result.timings``).

    Raises:
        ValueError: no edges, bad settings, or a non-positive-definite information matrix.
    """
    t_start = time.perf_counter()
    cfg = dataclasses.replace(config or OptimizerConfig(), **overrides)
    if isinstance(graph, PoseGraph) and graph.fixed.numel():  # the graph's own held poses (g2o FIX lines)
        cfg = dataclasses.replace(cfg, fixed=tuple(int(f) for f in cfg.fixed) + tuple(graph.fixed.tolist()))
    prev_threads = torch.get_num_threads()
    if cfg.num_threads is not None and cfg.num_threads != prev_threads:
        torch.set_num_threads(int(cfg.num_threads))
    try:
        with limit_blas_threads(cfg.num_threads if scipy_available() else None):
            if initialization != "none":  # (its time counts in timings["setup"])
                graph = initialize(graph, initialization, fixed=cfg.fixed)
            return _optimize(graph, method, kernel, solver, cfg, t_start)
    finally:
        if torch.get_num_threads() != prev_threads:
            torch.set_num_threads(prev_threads)


def _optimize(graph: PoseGraph, method: str, kernel, solver, cfg: OptimizerConfig,
              t_start: float) -> OptimizationResult:
    method = method.lower()
    if method not in ("lm", "gn"):
        raise ValueError(f"method must be 'lm' or 'gn', got {method!r}")
    if cfg.damping not in ("identity", "diagonal"):
        raise ValueError(f"damping must be 'identity' or 'diagonal', got {cfg.damping!r}")
    if cfg.lambda_update not in ("gtsam", "nielsen"):
        raise ValueError(f"lambda_update must be 'gtsam' or 'nielsen', got {cfg.lambda_update!r}")
    nielsen = method == "lm" and cfg.lambda_update == "nielsen"
    if method == "lm" and not (cfg.lambda_init > 0 and cfg.lambda_factor > 1 and cfg.lambda_max > cfg.lambda_init):
        raise ValueError("LM needs lambda_init > 0, lambda_factor > 1 and lambda_max > lambda_init, got "
                         f"{cfg.lambda_init}, {cfg.lambda_factor}, {cfg.lambda_max}")
    if cfg.dense_max is not None and cfg.dense_max < 0:
        raise ValueError(f"dense_max must be >= 0 or None, got {cfg.dense_max}")
    if not isinstance(graph, PoseGraph):
        raise TypeError(f"graph must be a PoseGraph, got {type(graph).__name__}")
    if graph.num_edges == 0:
        raise ValueError(f"the graph has no edges ({graph.num_poses} poses): there is nothing to optimise")
    if cfg.gauge not in ("free", "first", "prior"):
        raise ValueError(f"gauge must be 'free', 'first' or 'prior', got {cfg.gauge!r}")
    # GN has no damping to take care of a free gauge: it holds the first pose instead
    gauge = "first" if (method == "gn" and cfg.gauge == "free") else cfg.gauge
    kern = make_kernel(kernel, cfg.kernel_width)
    backend = _backend(graph, cfg, gauge)
    prob = _Problem(graph, cfg, kern, gauge, solver) if backend == "torch" else \
        _host_problem(graph, cfg, kern, gauge, solver, compiled=backend == "c")
    tm = {"setup": time.perf_counter() - t_start, "linearize": 0.0, "solve": 0.0, "evaluate": 0.0}

    t = time.perf_counter()
    x = prob.poses
    cost, chi2, cache = prob.evaluate(x)
    tm["evaluate"] += time.perf_counter() - t
    if not math.isfinite(cost):
        raise ValueError(f"the initial cost is {cost}: a pose, measurement or information matrix holds a "
                         "non-finite value")
    initial_chi2 = chi2
    history, lambdas, times = [cost], [], [time.perf_counter() - t_start]
    lam = cfg.lambda_init if method == "lm" else 0.0
    nu = 2.0  # Nielsen's growth factor of lambda after a rejected step
    status, message, it = Status.MAX_ITERATIONS, "", 0
    best = (cost, chi2, x, cache)
    if prob.size == 0:
        status, message = Status.CONVERGED, "every pose is fixed"
    while status == Status.MAX_ITERATIONS and it < cfg.max_iterations:
        if cost <= cfg.cost_tol:
            status = Status.CONVERGED
            break
        t = time.perf_counter()
        H, g = prob.linearize(x, cache)
        tm["linearize"] += time.perf_counter() - t
        accepted = False
        while not accepted:
            t = time.perf_counter()
            try:
                dx = prob.solve(H, g, lam)
                ok = True
            except LinearSolverError as exc:
                ok, message = False, str(exc)
            tm["solve"] += time.perf_counter() - t
            if ok:
                t = time.perf_counter()
                x_new = prob.retract(x, dx)
                cost_new, chi2_new, cache_new = prob.evaluate(x_new)
                tm["evaluate"] += time.perf_counter() - t
                ok = not math.isnan(cost_new)
            if method == "gn":
                if not ok:
                    status = Status.SOLVER_FAILED
                    break
                accepted = True
                if cost_new > cost:
                    status = Status.DIVERGED
                    message = f"GN step increased the cost {cost:.6g} -> {cost_new:.6g}"
            elif ok and cost_new < cost:
                accepted = True
            else:
                if nielsen:
                    lam, nu = lam * nu, nu * 2.0
                else:
                    lam *= cfg.lambda_factor
                if lam > cfg.lambda_max:
                    status = Status.LAMBDA_LIMIT
                    message = message or f"no decrease of the cost with lambda up to {cfg.lambda_max:g}"
                    break
        if not accepted:
            break
        it += 1
        decrease = cost - cost_new
        x, cost, chi2, cache = x_new, cost_new, chi2_new, cache_new
        history.append(cost)
        times.append(time.perf_counter() - t_start)
        lambdas.append(lam)
        if cost < best[0]:
            best = (cost, chi2, x, cache)
        if cfg.verbose:
            print(f"iter {it:3d}  cost {cost:.10g}  chi2 {chi2:.10g}  lambda {lam:.1e}")
        if nielsen:
            pred = prob.predicted_decrease(dx, g, lam)
            # gain ratio; clipped where the formula saturates anyway (and a broken model counts as poor)
            rho = min(max(decrease / pred, -1.0), 2.0) if pred > 0 else 0.0
            lam, nu = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), cfg.lambda_min), 2.0
        elif method == "lm":
            lam = max(lam / cfg.lambda_factor, cfg.lambda_min)
        if status == Status.DIVERGED:
            break
        if decrease < cfg.abs_tol or decrease < cfg.rel_tol * (cost + decrease) or cost <= cfg.cost_tol:
            status = Status.CONVERGED
    cost, chi2, x, cache = best
    x = prob.finish(x, it > 0)
    out_poses = x.to(dtype=graph.poses.dtype, device=graph.poses.device)
    result_graph = graph.with_poses(out_poses, check=False)  # finite: only finite costs are accepted
    tm["total"] = time.perf_counter() - t_start
    w = prob.weights(cache)
    return OptimizationResult(
        graph=result_graph, chi2=chi2, initial_chi2=initial_chi2, status=status, iterations=it,
        robust_cost=cost if kern is not None else None, cost_history=history, lambda_history=lambdas,
        time_history=times,
        timings=tm, weights=torch.ones(graph.num_edges, dtype=torch.float64) if w is None else w,
        message=message,
    )


class PoseGraphOptimizer:
    """A reusable optimiser holding its settings: ``PoseGraphOptimizer(method, kernel, **cfg)(graph)``.

    Example:
        >>> opt = PoseGraphOptimizer("lm", kernel="huber", max_iterations=20)
        >>> opt.config.max_iterations
        20
    """

    def __init__(self, method: str = "lm", kernel: Union[None, str, RobustKernel] = None,
                 solver: Union[None, str, LinearSolver] = "auto", config: Optional[OptimizerConfig] = None,
                 **overrides):
        self.method = method
        self.kernel = kernel
        self.solver = solver
        self.config = dataclasses.replace(config or OptimizerConfig(), **overrides)

    def __call__(self, graph: PoseGraph) -> OptimizationResult:
        return optimize(graph, self.method, self.kernel, self.solver, self.config)
