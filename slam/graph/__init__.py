"""Pose graphs: the :class:`PoseGraph` record, g2o I/O, residuals with robust kernels and the Gauss-Newton /
Levenberg-Marquardt optimiser over sparse normal equations.

Example:
    >>> import io
    >>> from slam.graph import read_g2o, optimize
    >>> text = "VERTEX_SE2 0 0 0 0\\nVERTEX_SE2 1 0.9 0 0\\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\\n"
    >>> g = read_g2o(io.StringIO(text))
    >>> res = optimize(g, method="lm")
    >>> res.graph.poses.shape, round(res.chi2, 9), str(res.status)
    (torch.Size([2, 7]), 0.0, 'converged')
"""
from slam.graph.config import OptimizerConfig
from slam.graph.costs import (
    CHI2_95_6DOF,
    Cauchy,
    GemanMcClure,
    Huber,
    RobustKernel,
    Tukey,
    edge_chi2,
    edge_jacobians,
    edge_residuals,
    graph_chi2,
    make_kernel,
)
from slam.graph.g2o import G2OFormatError, G2OWarning, read_g2o, write_g2o
from slam.graph.linear import DenseCholeskySolver, LinearSolver, SparseCholeskySolver
from slam.graph.optimizer import optimize
from slam.graph.pose_graph import PoseGraph
from slam.graph.result import OptimizationResult, Status

__all__ = [
    "CHI2_95_6DOF",
    "Cauchy",
    "DenseCholeskySolver",
    "G2OFormatError",
    "G2OWarning",
    "GemanMcClure",
    "Huber",
    "LinearSolver",
    "OptimizationResult",
    "OptimizerConfig",
    "PoseGraph",
    "RobustKernel",
    "SparseCholeskySolver",
    "Status",
    "Tukey",
    "edge_chi2",
    "edge_jacobians",
    "edge_residuals",
    "graph_chi2",
    "make_kernel",
    "optimize",
    "read_g2o",
    "write_g2o",
]
