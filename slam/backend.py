"""The SLAM back end: optimise the keyframe graph with a robust kernel per edge kind.

An odometry edge is rarely wrong by much, a loop edge is right or wrong altogether: by default Cauchy on the
odometry edges and dynamic covariance scaling (:class:`DCS`) on the loops, which switches off a wrong loop
(docs/pipeline.md, "What each stage does").

Example:
    >>> import torch
    >>> from slam.config import BackendConfig
    >>> from slam.keyframe_graph import EdgeKind, KeyframeGraph
    >>> from slam.lie import se3_exp, se3_identity
    >>> g = KeyframeGraph()
    >>> step = se3_exp(torch.tensor([1.0, 0, 0, 0, 0, 0.3], dtype=torch.float64))
    >>> _ = g.add_keyframe(se3_identity(dtype=torch.float64))
    >>> for k in range(1, 5):
    ...     _ = g.add_odometry(k - 1, step, torch.eye(6, dtype=torch.float64), g.odometry_pose(k - 1))
    >>> _ = g.add_loop(0, 4, se3_exp(torch.tensor([0.5, 3.0, 0, 0, 0, 1.2], dtype=torch.float64)),
    ...                torch.eye(6, dtype=torch.float64))
    >>> res = PoseGraphBackend(BackendConfig(), {EdgeKind.ODOMETRY: 1.0, EdgeKind.LOOP: 1.0}).optimize(g)
    >>> res.poses.shape, sorted(res.loop_weights)
    (torch.Size([5, 7]), [4])
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence

import torch

from slam.graph import CHI2_95_6DOF, RobustKernel, make_kernel, optimize
from slam.graph.optimizer import METHODS as OPTIMIZER_METHODS  # BackendConfig.method must be one of them
from slam.graph.optimizer import OptimizationResult
from slam.keyframe_graph import EdgeKind, KeyframeGraph
from slam.odometry.config import check_int, check_number  # the configs' shared range checks

Tensor = torch.Tensor

__all__ = ["DCS", "OPTIMIZER_METHODS", "BackendResult", "EdgeKindKernel", "PoseGraphBackend", "check_backend_config",
           "make_loop_kernel"]


@dataclass
class DCS(RobustKernel):
    """Dynamic covariance scaling (Agarwal et al. 2013) on ``s = r^T Omega r``: the closed form of a
    switchable constraint with prior ``phi``.

    ``rho(s) = s`` for ``s <= phi``, else ``phi (3 s - phi) / (phi + s)`` (bounded by ``3 phi``); the IRLS
    weight is ``(2 phi / (phi + s))^2``. ``width`` is ``sqrt(phi)`` (the Mahalanobis norm where it starts
    acting, as for the other kernels).
    """

    width: float = math.sqrt(CHI2_95_6DOF)
    name = "dcs"

    def __post_init__(self) -> None:
        if not self.width > 0:
            raise ValueError(f"DCS width must be > 0, got {self.width}")

    def rho_and_weight(self, s: Tensor):
        phi = self.width ** 2
        inl = s <= phi
        den = phi + s
        rho = torch.where(inl, s, phi * (3.0 * s - phi) / den)
        w = torch.where(inl, torch.ones_like(s), (2.0 * phi / den) ** 2)
        return rho, w


class EdgeKindKernel(RobustKernel):
    """A robust kernel per edge: ``kernels[k]`` on the edges whose kind code is ``k`` (None: quadratic).

    Args:
        kinds: ``(E,)`` int64 edge kinds in the graph's edge order (:meth:`KeyframeGraph.edge_kind_codes`).
        kernels: kind code -> :class:`~slam.graph.costs.RobustKernel` or None.
    """

    name = "per_kind"

    def __init__(self, kinds: Tensor, kernels: Dict[int, Optional[RobustKernel]]):
        self.kinds = kinds.to(torch.long)
        self.kernels = dict(kernels)
        # the edges of each kind, made once (the optimiser calls the kernel every step)
        self._rows = {k: torch.nonzero(self.kinds == k)[:, 0] for k, kern in self.kernels.items()
                      if kern is not None and bool((self.kinds == k).any())}

    def rho_and_weight(self, s: Tensor):
        if s.shape != self.kinds.shape:
            raise ValueError(f"EdgeKindKernel: {tuple(s.shape)} squared norms for {self.kinds.numel()} edges")
        if len(self._rows) == 1 and next(iter(self._rows.values())).numel() == s.numel():
            return self.kernels[next(iter(self._rows))](s)  # one kind only: no scatter
        rho, w = s.clone(), torch.ones_like(s)
        for k, rows in self._rows.items():
            rows = rows.to(s.device)
            r_k, w_k = self.kernels[k](s.index_select(0, rows))
            rho.index_copy_(0, rows, r_k.to(s.dtype))
            w.index_copy_(0, rows, w_k.to(s.dtype))
        return rho, w


def make_loop_kernel(name: Optional[str], width: Optional[float]) -> Optional[RobustKernel]:
    """The loop edges' kernel by name: ``"dcs"``, a kernel of :func:`slam.graph.make_kernel`, or None."""
    if name is not None and name.lower() == "dcs":
        return DCS() if width is None else DCS(width)
    return make_kernel(name, width)


def check_backend_config(config) -> None:
    """Refuse a :class:`slam.config.BackendConfig` the back end could not run, when it is built.

    Raises:
        ValueError: naming the field, the value and what is allowed.
    """
    n = "BackendConfig"
    if not (isinstance(config.method, str) and config.method.lower() in OPTIMIZER_METHODS):
        raise ValueError(f"{n}.method must be one of {', '.join(map(repr, OPTIMIZER_METHODS))}, got {config.method!r}")
    for field_name in ("kernel_width", "loop_kernel_width"):
        width = getattr(config, field_name)
        if width is not None:
            check_number(n, field_name, width, 0, lo_open=True, finite=True)
    try:
        make_kernel(config.kernel, config.kernel_width)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{n}.kernel must be a kernel name of slam.graph.make_kernel or None, got "
                         f"{config.kernel!r} ({exc})") from None
    if config.loop_kernel is not None:
        try:
            if not isinstance(config.loop_kernel, str):
                raise TypeError(f"a name, not {type(config.loop_kernel).__name__}")
            make_loop_kernel(config.loop_kernel, config.loop_kernel_width)
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{n}.loop_kernel: unknown loop kernel {config.loop_kernel!r}; expected 'dcs', "
                             f"a kernel name of slam.graph.make_kernel, 'none' or None ({exc})") from None
    for name, least in (("max_iterations", 1), ("loop_backlog", 0), ("online_max_iterations", 1)):
        check_int(n, name, getattr(config, name), least)
    for name in ("online_window", "online_loops_per_keyframe"):  # None: off
        if getattr(config, name) is not None:
            check_int(n, name, getattr(config, name), 1)
    check_number(n, "odometry_information_scale", config.odometry_information_scale, 0, lo_open=True, finite=True)
    check_number(n, "switch_off_weight", config.switch_off_weight, 0, 1)


@dataclass
class BackendResult:
    """What :meth:`PoseGraphBackend.optimize` returns.

    Attributes:
        poses: ``(M, 7)`` float64 optimised keyframe poses.
        loop_weights: index into ``KeyframeGraph.edges`` -> final kernel weight of that (active) loop
            edge (1 = fully trusted, near 0 = switched off).
        status: the optimiser's status.
        iterations: LM iterations.
        seconds: wall time.
        initial_chi2, chi2: of the graph (plain sums, before and after).
        optimization: the :class:`~slam.graph.optimizer.OptimizationResult`.
        history: the cost after each iteration.
    """

    poses: Tensor
    loop_weights: Dict[int, float]
    status: str
    iterations: int
    seconds: float
    initial_chi2: float
    chi2: float
    optimization: Optional[OptimizationResult] = None
    history: List[float] = field(default_factory=list)


class PoseGraphBackend:
    """Optimises a :class:`~slam.keyframe_graph.KeyframeGraph`.

    Args:
        config: :class:`slam.config.BackendConfig`.
        information_scale: edge kind -> factor on the registration's information.
    """

    def __init__(self, config, information_scale: Dict[EdgeKind, float]):
        self.config = config
        self.information_scale = dict(information_scale)
        check_backend_config(config)  # any object with these fields, not only a (frozen, checked) BackendConfig

    def optimize(self, graph: KeyframeGraph, *, online: bool = False, fixed: Optional[Sequence[int]] = None,
                 free: Optional[Sequence[int]] = None) -> BackendResult:
        """Optimise the active edges of ``graph`` from its current estimates.

        Args:
            graph: the keyframe graph (not modified).
            online: a correction during tracking: at most ``config.online_max_iterations`` LM iterations.
            fixed: keyframes held at their start poses (a loaded map's); they then anchor the result (else
                keyframe 0 does).
            free: optimise only these keyframes (:meth:`KeyframeGraph.window_graph`, an online one with the newest
                ``BackendConfig.online_loops_per_keyframe`` loops of each): the keyframes the window's edges reach
                are held, the others returned unchanged, and only the window's loops are in ``loop_weights``.
                None (or every keyframe): the whole graph.

        Returns:
            :class:`BackendResult`.

        Raises:
            ValueError: the graph has no keyframes or no edges.
        """
        cfg = self.config
        t0 = time.perf_counter()
        window = None
        if free is not None:
            window = graph.window_graph(self.information_scale, free,
                                        loops_per_keyframe=cfg.online_loops_per_keyframe if online else None,
                                        fixed=fixed)
        if window is not None:  # its edges are never empty: a window without one holds nothing and is None
            pg, used, rows = window
        else:
            pg = graph.pose_graph(self.information_scale)
            if pg is None or pg.num_edges == 0:
                raise ValueError("the keyframe graph has no edges to optimise")
            if fixed:
                pg = dataclasses.replace(pg, fixed=torch.as_tensor(list(fixed), dtype=torch.long))
            used, rows = None, torch.tensor([k for k, e in enumerate(graph.edges) if e.active], dtype=torch.long)
        kinds, active = graph.edge_kind_codes(rows), rows.tolist()
        if cfg.device is not None:  # BackendConfig.device: solved there, returned on the CPU
            pg = pg.to(cfg.device)
        kinds = kinds.to(pg.device)
        loop_rows = [r for r, k in enumerate(active) if graph.edges[k].kind is EdgeKind.LOOP]
        iters = cfg.online_max_iterations if online else cfg.max_iterations
        loop_kernel = (make_kernel(cfg.kernel, cfg.kernel_width) if cfg.loop_kernel is None  # as the odometry's
                       else make_loop_kernel(cfg.loop_kernel, cfg.loop_kernel_width))
        kernel = EdgeKindKernel(kinds, {int(EdgeKind.ODOMETRY): make_kernel(cfg.kernel, cfg.kernel_width),
                                        int(EdgeKind.LOOP): loop_kernel})
        res = optimize(pg, method=cfg.method, kernel=kernel, max_iterations=iters)
        loop_weights = {active[r]: float(res.weights[r]) for r in loop_rows}  # (E,) weights, ones without a kernel
        poses = res.graph.poses.detach().to(torch.float64).cpu()
        if used is not None:  # into the whole graph: the keyframes outside the window (held ones too) as they were
            moved = torch.ones(used.numel(), dtype=torch.bool)
            moved[pg.fixed.cpu()] = False
            poses = graph.estimates().index_copy_(0, used[moved], poses[moved])
        return BackendResult(poses, loop_weights, str(res.status), res.iterations, time.perf_counter() - t0,
                             float(res.initial_chi2), float(res.chi2), res, list(res.cost_history))
