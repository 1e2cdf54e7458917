"""What the pose-graph optimiser returns: :class:`OptimizationResult` and its :class:`Status`."""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Dict, List, Optional

import torch

from slam.graph.pose_graph import PoseGraph

__all__ = ["OptimizationResult", "Status"]

Tensor = torch.Tensor


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
class OptimizationResult:
    """What :func:`optimize` returns.

    Attributes:
        graph: the optimised :class:`PoseGraph` (same edges, new poses ``(N, 7)``; input dtype/device).
        chi2: final ``sum r^T Omega r`` (GTSAM error = ``0.5 * chi2``), without the prior of the gauge.
        initial_chi2: the same at the initial poses.
        robust_cost: final ``sum rho(s)`` when a kernel was used, else ``None``.
        status: a :class:`Status`.
        iterations: outer iterations done (accepted LM steps / GN steps).
        cost_history: the optimised cost after each iteration, starting with the initial one.
        lambda_history: LM damping used for each accepted step.
        time_history: seconds since the call started at which each entry of ``cost_history`` was known.
        timings: seconds spent in ``setup``, ``linearize``, ``solve``, ``evaluate`` and ``total``.
        weights: ``(E,)`` final kernel weights (all ones without a kernel): near 0 marks a rejected edge.
        message: why the optimiser stopped, where a status alone does not say.
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
