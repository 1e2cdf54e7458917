"""Gauss-Newton and Levenberg-Marquardt for pose graphs over sparse normal equations.

Each iteration linearises every edge at once (:class:`~slam.graph.problem.TorchProblem`), solves
``(H + lambda D) dx = -g`` on a fixed sparse pattern and retracts ``T <- T exp(dx)`` (right perturbation);
here is the outer loop with its step rules (Gauss-Newton, LM with GTSAM's schedule or Nielsen's rule).

Gauge: ``"free"`` (LM's default) leaves it to the LM damping, as GTSAM does without a prior, then moves the
result rigidly so that pose 0 keeps its initial value; ``"first"`` holds pose 0 (GN always does);
``"prior"`` adds a strong prior on pose 0. Poses in ``fixed`` are held too (and then anchor the result).
A planar graph (z = roll = pitch = 0) is solved in (x, y, yaw) only: the problem splits exactly.

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
import warnings
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Tuple, Union

import torch

from slam.graph.config import OptimizerConfig
from slam.graph.costs import RobustKernel, make_kernel
from slam.graph.initialization import fits_edges, initial_poses, initialize
from slam.graph.linear import LinearSolver, LinearSolverError
from slam.graph.pose_graph import PoseGraph
from slam.graph.problem import TorchProblem
from slam.graph.result import OptimizationResult, Status
from slam.lie import se3_normalize

__all__ = ["METHODS", "OptimizationResult", "OptimizerConfig", "Status", "optimize"]

#: The outer loops :func:`optimize` runs (case-insensitive): Levenberg-Marquardt, Gauss-Newton.
METHODS = ("lm", "gn")
LAMBDA_MIN = 1e-12  # LM's lambda is clamped above this

Tensor = torch.Tensor


def optimize(graph: PoseGraph, method: str = "lm", kernel: Union[None, str, RobustKernel] = None,
             solver: Union[None, str, LinearSolver] = "auto", config: Optional[OptimizerConfig] = None,
             initialization: str = "none", **overrides) -> OptimizationResult:
    """Optimise the poses of a pose graph.

    Args:
        graph: the :class:`PoseGraph`; its ``poses (N, 7)`` are the initial guess (they are not modified).
        method: ``"lm"`` (Levenberg-Marquardt) or ``"gn"`` (Gauss-Newton).
        kernel: ``None``, a name (``"huber"``, ``"cauchy"``, ``"tukey"``, ``"geman_mcclure"``) or a
            :class:`~slam.graph.costs.RobustKernel` object.
        solver: ``"auto"`` (dense Cholesky for small systems, else sparse), ``"sparse"``, ``"dense"`` or a
            :class:`~slam.graph.linear.LinearSolver` object.
        config: an :class:`OptimizerConfig`; keyword ``overrides`` replace its fields
            (e.g. ``optimize(g, max_iterations=10, gauge="prior")``).
        initialization: the initial guess: ``"none"`` (the graph's poses), ``"chordal"``, ``"spanning_tree"``
            or ``"auto"`` (see :mod:`slam.graph.initialization`); ``initial_chi2`` is that guess's chi2.

    Returns:
        An :class:`OptimizationResult`. With ``differentiable=True``, ``result.graph.poses`` carries a
        ``grad_fn`` when the graph's measurements, information or held poses require grad.

    Raises:
        ValueError: no edges, bad settings, or a non-positive-definite information matrix.
    """
    t_start = time.perf_counter()
    cfg = dataclasses.replace(config or OptimizerConfig(), **overrides)
    if isinstance(graph, PoseGraph) and graph.fixed.numel():  # the graph's own held poses (g2o FIX lines)
        cfg = dataclasses.replace(cfg, fixed=tuple(int(f) for f in cfg.fixed) + tuple(graph.fixed.tolist()))
    if initialization not in ("none", "auto"):  # (its time counts in timings["setup"]; "auto" below)
        given = graph.poses
        graph = initialize(graph, initialization, fixed=cfg.fixed)
        if given.requires_grad:  # the anchors' rows stay the caller's tensor (their gradient is kept)
            same = (graph.poses == given.detach()).all(dim=-1, keepdim=True)
            graph = graph.with_poses(torch.where(same, given, graph.poses), check=False)
    method = method.lower()
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    cfg.validate(method)
    if not isinstance(graph, PoseGraph):
        raise TypeError(f"graph must be a PoseGraph, got {type(graph).__name__}")
    if graph.num_edges == 0:
        raise ValueError(f"the graph has no edges ({graph.num_poses} poses): there is nothing to optimise")
    # GN has no damping to take care of a free gauge: it holds the first pose instead
    gauge = "first" if (method == "gn" and cfg.gauge == "free") else cfg.gauge
    kern = make_kernel(kernel, cfg.kernel_width)
    prob = TorchProblem(graph, cfg, kern, gauge, solver)
    start = None
    if initialization == "auto":  # the graph's poses, evaluated once, unless they fit the edges too poorly
        start = prob.evaluate(prob.poses)
        if not fits_edges(start[1], graph.num_edges):
            tree = initial_poses(graph, "spanning_tree", cfg.fixed).detach().to(prob.poses)
            prob.poses, start = se3_normalize(tree, positive_w=False), None
    tm = {"setup": time.perf_counter() - t_start, "linearize": 0.0, "solve": 0.0, "evaluate": 0.0}
    run = _minimize(prob, method, cfg, tm, t_start, start)
    x = prob.finish(run.best.x, run.iterations > 0)
    prob.release()
    if cfg.differentiable:
        from slam.graph.implicit import attach_gradients

        # (GN's "diverged" is also how it ends at an optimum with tight tolerances: a round-off step)
        if run.status in (Status.MAX_ITERATIONS, Status.SOLVER_FAILED):
            warnings.warn(f"optimize(differentiable=True) stopped with status {run.status} after {run.iterations} "
                          "iteration(s): the implicit gradients are those of the optimum, not of the poses "
                          "returned; optimise to convergence (max_iterations, rel_tol) for gradients that "
                          "match them", RuntimeWarning, stacklevel=2)
        x = attach_gradients(graph, x, cfg, kern, gauge, solver)
    result_graph = graph.with_poses(x.to(dtype=graph.poses.dtype, device=graph.poses.device),
                                    check=False)  # finite: only finite costs are accepted
    tm["total"] = time.perf_counter() - t_start
    w = run.best.cache[2]  # the kernel weights (None without a kernel)
    res = OptimizationResult(
        graph=result_graph, chi2=run.best.chi2, initial_chi2=run.initial_chi2, status=run.status,
        iterations=run.iterations, robust_cost=run.best.cost if kern is not None else None,
        cost_history=run.costs, lambda_history=run.lambdas, time_history=run.times, timings=tm,
        weights=torch.ones(graph.num_edges, dtype=torch.float64) if w is None else w, message=run.message)
    if res.status == Status.MAX_ITERATIONS and res.iterations:
        res.message = _stall_advice(res, cfg, initialization)
    return res


def _stall_advice(res: OptimizationResult, cfg: OptimizerConfig, initialization: str) -> str:
    """Why a run stopped at ``max_iterations`` and what to try (``OptimizationResult.message``)."""
    last = (res.cost_history[-2] - res.cost_history[-1]) / res.cost_history[-2]
    text = (f"stopped at max_iterations={cfg.max_iterations} with the cost still falling ({last:.2g} of it in the "
            f"last iteration; converged means < rel_tol={cfg.rel_tol:g})")
    if initialization == "none":
        return (text + "; if the initial guess is far from the optimum (raw odometry over a long trajectory), try "
                "initialization='chordal' (or 'spanning_tree'), else more iterations")
    return text + ": try more iterations, or damping='diagonal' with lambda_update='nielsen'"


@dataclass
class _Iterate:
    """Poses ``x`` with their cost, chi2 and the problem's cache (and the step ``dx`` that led there)."""

    cost: float
    chi2: float
    x: Any
    cache: Any
    dx: Any = None


@dataclass
class _Run:
    """What the outer loop hands back to :func:`optimize`."""

    best: _Iterate
    initial_chi2: float
    status: Status
    iterations: int
    message: str
    costs: List[float]
    lambdas: List[float]
    times: List[float]


class _GtsamDamping:
    """LM's lambda on GTSAM's schedule: ``/= lambda_factor`` after an accepted step, ``*=`` after a rejected one."""

    def __init__(self, cfg: OptimizerConfig):
        self.cfg, self.lam = cfg, cfg.lambda_init

    def reject(self) -> bool:
        """Grow lambda after a rejected step; False once it passes ``lambda_max``."""
        self.lam *= self.cfg.lambda_factor
        return self.lam <= self.cfg.lambda_max

    def accept(self, prob: TorchProblem, dx, g, decrease: float) -> None:
        self.lam = max(self.lam / self.cfg.lambda_factor, LAMBDA_MIN)


class _NielsenDamping(_GtsamDamping):
    """Nielsen's gain-ratio rule (g2o, Ceres): after a step with gain ratio ``rho`` (actual / predicted
    decrease) ``lambda *= max(1/3, 1 - (2 rho - 1)^3)``; after a rejected one ``lambda *= nu``, ``nu`` doubling."""

    def __init__(self, cfg: OptimizerConfig):
        super().__init__(cfg)
        self.nu = 2.0

    def reject(self) -> bool:
        self.lam, self.nu = self.lam * self.nu, self.nu * 2.0
        return self.lam <= self.cfg.lambda_max

    def accept(self, prob: TorchProblem, dx, g, decrease: float) -> None:
        pred = prob.predicted_decrease(dx, g, self.lam)
        # gain ratio; clipped where the formula saturates anyway (and a broken model counts as poor)
        rho = min(max(decrease / pred, -1.0), 2.0) if pred > 0 else 0.0
        self.lam = max(self.lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), LAMBDA_MIN)
        self.nu = 2.0


#: LM's damping strategies by ``OptimizerConfig.lambda_update``
DAMPING = {"gtsam": _GtsamDamping, "nielsen": _NielsenDamping}


def _trial(prob: TorchProblem, x, H, g, lam: float, tm: Dict[str, float]) -> Tuple[Optional[_Iterate], str]:
    """The step of ``(H + lambda D) dx = -g`` from ``x`` and its cost; None (and why) when the solve fails or
    the cost is NaN."""
    t = time.perf_counter()
    try:
        dx = prob.solve(H, g, lam)
    except LinearSolverError as exc:
        tm["solve"] += time.perf_counter() - t
        return None, str(exc)
    tm["solve"] += time.perf_counter() - t
    t = time.perf_counter()
    x_new = prob.retract(x, dx)
    cost, chi2, cache = prob.evaluate(x_new)
    tm["evaluate"] += time.perf_counter() - t
    if math.isnan(cost):
        return None, "a step gave a NaN cost"
    return _Iterate(cost, chi2, x_new, cache, dx), ""


def _lm_step(prob: TorchProblem, cur: _Iterate, H, g, damping: _GtsamDamping, cfg: OptimizerConfig,
             tm: Dict[str, float]) -> Tuple[Optional[_Iterate], str]:
    """Damped steps from ``cur``, lambda growing, until one lowers the cost; None (and why) when lambda
    passes ``lambda_max`` first."""
    while True:
        trial, message = _trial(prob, cur.x, H, g, damping.lam, tm)
        if trial is not None and trial.cost < cur.cost:
            return trial, ""
        if not damping.reject():
            return None, message or f"no decrease of the cost with lambda up to {cfg.lambda_max:g}"


def _minimize(prob: TorchProblem, method: str, cfg: OptimizerConfig, tm: Dict[str, float],
              t_start: float, start=None) -> _Run:
    """Gauss-Newton or Levenberg-Marquardt iterations on ``prob`` from its initial poses (``start``: their
    ``prob.evaluate`` when already made)."""
    t = time.perf_counter()
    cost, chi2, cache = prob.evaluate(prob.poses) if start is None else start
    cur = _Iterate(cost, chi2, prob.poses, cache)
    tm["evaluate"] += time.perf_counter() - t
    if not math.isfinite(cost):
        raise ValueError(f"the initial cost is {cost}: a pose, measurement or information matrix holds a "
                         "non-finite value")
    run = _Run(cur, chi2, Status.MAX_ITERATIONS, 0, "", [cost], [], [time.perf_counter() - t_start])
    damping = DAMPING[cfg.lambda_update](cfg) if method == "lm" else None  # None: Gauss-Newton
    if prob.size == 0:
        run.status, run.message = Status.CONVERGED, "every pose is fixed"
    while run.status == Status.MAX_ITERATIONS and run.iterations < cfg.max_iterations:
        t = time.perf_counter()
        H, g = prob.linearize(cur.x, cur.cache)
        tm["linearize"] += time.perf_counter() - t
        if damping is None:  # Gauss-Newton: every step is taken
            new, run.message = _trial(prob, cur.x, H, g, 0.0, tm)
            if new is None:
                run.status = Status.SOLVER_FAILED
                break
            if new.cost > cur.cost:
                run.status = Status.DIVERGED
                run.message = f"GN step increased the cost {cur.cost:.6g} -> {new.cost:.6g}"
        else:
            new, run.message = _lm_step(prob, cur, H, g, damping, cfg, tm)
            if new is None:
                run.status = Status.LAMBDA_LIMIT
                break
        run.iterations += 1
        decrease = cur.cost - new.cost
        cur = new
        run.costs.append(cur.cost)
        run.times.append(time.perf_counter() - t_start)
        run.lambdas.append(0.0 if damping is None else damping.lam)
        if cur.cost < run.best.cost:
            run.best = cur
        if cfg.verbose:
            print(f"iter {run.iterations:3d}  cost {cur.cost:.10g}  chi2 {cur.chi2:.10g}  "
                  f"lambda {run.lambdas[-1]:.1e}")
        if damping is not None:
            damping.accept(prob, cur.dx, g, decrease)
        if run.status == Status.DIVERGED:
            break
        if decrease < cfg.abs_tol or decrease < cfg.rel_tol * (cur.cost + decrease):
            run.status = Status.CONVERGED
    return run
