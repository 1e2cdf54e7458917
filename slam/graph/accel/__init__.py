"""The optimiser's optional CPU accelerator: the per-edge maths of the torch reference (:mod:`slam.graph.fused`)
again in numpy, and in C where the extension was built (``slam.graph.accel._kernels``).

Why: on the CPU a torch eager call costs 1.2-2 us of dispatch, and an LM iteration is ~150 of them whatever
the graph's size. On graphs of a few hundred poses that overhead is most of the run time (tinyGrid3D: torch
~5 ms, the numpy functions ~1.3 ms, the C kernels ~0.4 ms); on thousands of poses the shared sparse
Cholesky dominates and the backends are within ~30 % of each other (docs/benchmarks.md, "Pose graph").

Each accelerator satisfies :class:`Accelerator` and builds a :class:`~slam.graph.problem.PoseGraphProblem`
that the outer loop drives exactly like the torch one; the tests check that they take the same steps as
:class:`~slam.graph.problem.TorchProblem` to round-off (``tests/test_graph_host.py``,
``tests/test_graph_kernels.py``). :data:`ACCELERATORS` holds them by name (``"c"``, ``"numpy"``: the
``backend`` names of :class:`~slam.graph.config.OptimizerConfig`).

Example:
    >>> sorted(ACCELERATORS), ACCELERATORS["numpy"].available()
    (['c', 'numpy'], True)
"""
from __future__ import annotations

from typing import Dict, List, Optional, Protocol, runtime_checkable

from slam.graph.accel import _compiled

__all__ = ["ACCELERATORS", "Accelerator", "HostAccelerator", "accelerator_for", "compiled_kernels"]


def compiled_kernels() -> bool:
    """Whether the C kernels (``slam.graph.accel._kernels``) were built and imported."""
    return _compiled.kernels is not None


@runtime_checkable
class Accelerator(Protocol):
    """A faster implementation of the optimiser's per-edge maths for some graphs.

    Attributes:
        name: its ``OptimizerConfig.backend`` name.
    """

    name: str

    def available(self) -> bool:
        """Whether it can run in this installation."""

    def unsupported(self, graph, cfg, gauge: str) -> List[str]:
        """Why it cannot optimise ``graph`` with ``cfg`` and the resolved ``gauge`` ([] when it can)."""

    def problem(self, graph, cfg, kernel, gauge: str, solver):
        """The :class:`~slam.graph.problem.PoseGraphProblem` of one optimisation (the arguments of
        :class:`~slam.graph.problem.TorchProblem`)."""


class HostAccelerator:
    """The numpy functions of :mod:`slam.graph.accel.host`, with its C kernels when ``compiled``.

    Args:
        compiled: use the C kernels (per-edge work and the sparse Cholesky's small fronts).
    """

    def __init__(self, compiled: bool):
        self.compiled = compiled
        self.name = "c" if compiled else "numpy"

    def available(self) -> bool:
        return compiled_kernels() if self.compiled else True

    def unsupported(self, graph, cfg, gauge: str) -> List[str]:
        return [why for bad, why in ((graph.poses.device.type != "cpu", f"device {graph.poses.device}"),
                                     (graph.chart != "se3", f"chart {graph.chart!r}"),
                                     (gauge == "prior", "gauge 'prior'")) if bad]

    def problem(self, graph, cfg, kernel, gauge: str, solver):
        from slam.graph.accel.host import host_problem

        return host_problem(graph, cfg, kernel, gauge, solver, compiled=self.compiled)

    def __repr__(self) -> str:
        return f"HostAccelerator(compiled={self.compiled})"


ACCELERATORS: Dict[str, Accelerator] = {"c": HostAccelerator(True), "numpy": HostAccelerator(False)}


def accelerator_for(graph, cfg, gauge: str) -> Optional[Accelerator]:
    """The accelerator ``cfg.backend`` asks for (``"auto"``: C, else numpy), or None for the torch path;
    a ``ValueError`` says why a required one (``"c"``, ``"numpy"``) cannot run this graph."""
    if cfg.backend == "torch":
        return None
    if cfg.backend == "c" and not compiled_kernels():
        raise ValueError("backend 'c' needs the C kernels slam.graph.accel._kernels, which were not built "
                         "(install attnloop where a C compiler is found); use backend='numpy' or 'auto'")
    name = cfg.backend if cfg.backend != "auto" else ("c" if compiled_kernels() else "numpy")
    acc = ACCELERATORS[name]
    why = acc.unsupported(graph, cfg, gauge)
    if why and cfg.backend != "auto":
        raise ValueError(f"backend {cfg.backend!r} does not support {', '.join(why)}; use backend='torch'")
    return None if why else acc
