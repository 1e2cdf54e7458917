"""Pose-graph residuals, their analytic Jacobians (checked wrappers of :mod:`slam.graph.fused`), and robust
kernels, vectorised over edges.

With ``D = z^-1 T_i^-1 T_j`` the residual ``r (6,)`` ``[rho, phi]`` is ``Log(D)`` (chart ``"se3"``: GTSAM's
``BetweenFactor``) or ``[t(D), Log_SO3(R(D))]`` (``"r3so3"``: g2o's ``EDGE_SE2``), Jacobians w.r.t. right
perturbations. A kernel maps ``s = r^T Omega r`` to the cost ``rho(s)`` and the IRLS weight ``rho'(s)``.

Example:
    >>> import torch
    >>> from slam.lie import se3_exp
    >>> poses = se3_exp(torch.randn(4, 6, dtype=torch.float64) * 0.1)
    >>> ii, jj = torch.tensor([0, 1, 2]), torch.tensor([1, 2, 3])
    >>> r, D = edge_residuals(poses, ii, jj, se3_exp(torch.zeros(3, 6, dtype=torch.float64)))
    >>> Ji, Jj = edge_jacobians(poses, ii, jj, D, r)
    >>> r.shape, Ji.shape, Jj.shape
    (torch.Size([3, 6]), torch.Size([3, 6, 6]), torch.Size([3, 6, 6]))
    >>> Huber(1.0)(torch.tensor([0.25, 4.0]))
    (tensor([0.2500, 3.0000]), tensor([1.0000, 0.5000]))
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple, Union

import torch

from slam.graph import fused
from slam.lie import se3_between, se3_compose, se3_inv

__all__ = [
    "CHI2_95_6DOF",
    "Cauchy",
    "GemanMcClure",
    "Huber",
    "RobustKernel",
    "Tukey",
    "edge_chi2",
    "edge_jacobians",
    "edge_residuals",
    "graph_chi2",
    "make_kernel",
]

Tensor = torch.Tensor

# 95% quantile of the chi-square distribution with 6 degrees of freedom (of s = r^T Omega r on an inlier edge)
CHI2_95_6DOF = 12.591587243743977


def _check_edges(poses: Tensor, ii: Tensor, jj: Tensor, measurements: Tensor) -> None:
    if poses.dim() != 2 or poses.shape[-1] != 7:
        raise ValueError(f"poses must have shape (N, 7), got {tuple(poses.shape)}")
    if ii.dim() != 1 or ii.shape != jj.shape:
        raise ValueError(f"ii and jj must have shape (E,), got {tuple(ii.shape)} and {tuple(jj.shape)}")
    if measurements.shape != (ii.shape[0], 7):
        raise ValueError(f"measurements must have shape (E, 7) = ({ii.shape[0]}, 7), got "
                         f"{tuple(measurements.shape)}")


def edge_residuals(poses: Tensor, ii: Tensor, jj: Tensor, measurements: Tensor,
                   chart: str = "se3") -> Tuple[Tensor, Tensor]:
    """Residuals of all edges (differentiable).

    Args:
        poses: ``(N, 7)`` poses.
        ii, jj: ``(E,)`` long, the first and second pose of each edge.
        measurements: ``(E, 7)`` measured ``z_ij ~= T_i^-1 T_j``.
        chart: ``"se3"`` or ``"r3so3"`` (see the module docstring).

    Returns:
        ``r (E, 6)`` in the ``[rho, phi]`` order and the error poses ``D = z^-1 T_i^-1 T_j (E, 7)``
        (reused by :func:`edge_jacobians`).
    """
    _check_edges(poses, ii, jj, measurements)
    r, aux = fused.se3_residuals(poses, ii, jj, se3_inv(measurements), chart)
    return r, torch.cat([aux[2], aux[3]], dim=-1)


def edge_jacobians(poses: Tensor, ii: Tensor, jj: Tensor, D: Tensor, r: Tensor,
                   chart: str = "se3") -> Tuple[Tensor, Tensor]:
    """Analytic Jacobians of the residuals w.r.t. right perturbations of ``T_i`` and ``T_j``.

    Args:
        poses: ``(N, 7)`` poses.
        ii, jj: ``(E,)`` long, the first and second pose of each edge.
        D: ``(E, 7)`` error poses from :func:`edge_residuals`.
        r: ``(E, 6)`` residuals from :func:`edge_residuals`.
        chart: the chart ``r`` was computed in.

    Returns:
        ``J_i (E, 6, 6)`` and ``J_j (E, 6, 6)`` with
        ``r(T_i exp(d_i), T_j exp(d_j)) ~= r + J_i d_i + J_j d_j``.
    """
    if chart == "se3":
        zinv = se3_compose(D, se3_between(poses[jj], poses[ii]))
        _, theta2, c = fused._log_terms(D[:, 3:])
        JT = fused.se3_jacobians_t(r, (theta2, c), -fused.se3_adjoint_t(zinv))
        return JT[:, :6].transpose(1, 2), JT[:, 6:12].transpose(1, 2)
    if chart == "r3so3":
        return fused.r3so3_jacobians(poses, ii, jj, D[:, 3:], r)
    raise ValueError(f"chart must be 'se3' or 'r3so3', got {chart!r}")


def edge_chi2(r: Tensor, information: Tensor) -> Tensor:
    """Squared Mahalanobis norms ``s = r^T Omega r`` ``(E,)`` of residuals ``(E, 6)``."""
    return torch.einsum("ei,eij,ej->e", r, information, r)


def graph_chi2(graph) -> float:
    """``sum_e r_e^T Omega_e r_e`` of a :class:`~slam.graph.pose_graph.PoseGraph` at its poses (GTSAM's error
    is half of it)."""
    if graph.num_edges == 0:
        return 0.0
    r, _ = edge_residuals(graph.poses, graph.ii, graph.jj, graph.measurements, graph.chart)
    return float(edge_chi2(r, graph.information).sum())


class RobustKernel:
    """Base class: ``kernel(s) -> (rho(s), w(s) = rho'(s))`` for squared Mahalanobis norms ``s (E,)``;
    subclasses implement :meth:`rho_and_weight`."""

    def rho_and_weight(self, s: Tensor) -> Tuple[Tensor, Tensor]:  # pragma: no cover - abstract
        raise NotImplementedError

    def __call__(self, s: Tensor) -> Tuple[Tensor, Tensor]:
        if not isinstance(s, Tensor) or s.dim() != 1:
            raise ValueError(f"s must be a tensor of shape (E,), got {getattr(s, 'shape', type(s))}")
        return self.rho_and_weight(s)


@dataclass
class _Width(RobustKernel):
    width: float = math.sqrt(CHI2_95_6DOF)  # kernel width on the Mahalanobis norm sqrt(s)

    def __post_init__(self) -> None:
        if not self.width > 0:
            raise ValueError(f"{type(self).__name__} width must be > 0, got {self.width}")


@dataclass
class Huber(_Width):
    """Huber: quadratic up to ``sqrt(s) = width``, linear beyond (``rho = 2 d sqrt(s) - d^2``)."""

    def rho_and_weight(self, s: Tensor) -> Tuple[Tensor, Tensor]:
        d2 = self.width ** 2
        e = torch.sqrt(s.clamp_min(d2))  # >= width: no 0 division on the quadratic branch
        inl = s <= d2
        rho = torch.where(inl, s, 2.0 * self.width * e - d2)
        w = torch.where(inl, torch.ones_like(s), self.width / e)
        return rho, w


@dataclass
class Cauchy(_Width):
    """Cauchy (Lorentzian): ``rho = c^2 log(1 + s / c^2)``, ``w = 1 / (1 + s / c^2)``."""

    def rho_and_weight(self, s: Tensor) -> Tuple[Tensor, Tensor]:
        c2 = self.width ** 2
        return c2 * torch.log1p(s / c2), 1.0 / (1.0 + s / c2)


@dataclass
class Tukey(_Width):
    """Tukey biweight: ``rho = c^2/3 (1 - (1 - s/c^2)^3)`` inside ``s < c^2``, constant outside (w = 0)."""

    def rho_and_weight(self, s: Tensor) -> Tuple[Tensor, Tensor]:
        c2 = self.width ** 2
        u = (1.0 - s / c2).clamp_min(0.0)
        return c2 / 3.0 * (1.0 - u ** 3), u * u


@dataclass
class GemanMcClure(_Width):
    """Geman-McClure: ``rho = c^2 s / (c^2 + s)``, ``w = c^4 / (c^2 + s)^2``."""

    def rho_and_weight(self, s: Tensor) -> Tuple[Tensor, Tensor]:
        c2 = self.width ** 2
        den = c2 + s
        return c2 * s / den, (c2 / den) ** 2


_KERNELS = {"huber": Huber, "cauchy": Cauchy, "tukey": Tukey, "geman_mcclure": GemanMcClure,
            "gm": GemanMcClure}


def make_kernel(kernel: Union[None, str, RobustKernel],
                width: Optional[float] = None) -> Optional[RobustKernel]:
    """A kernel object from a name (``"huber"``, ``"cauchy"``, ``"tukey"``, ``"geman_mcclure"``), an
    object (returned as is) or ``None``/``"none"`` (returns ``None``); ``width`` on ``sqrt(s)`` for a kernel
    made from a name (default ``sqrt(chi2_0.95(6)) = 3.55``)."""
    if kernel is None:
        return None
    if isinstance(kernel, RobustKernel):
        return kernel
    if isinstance(kernel, str):
        key = kernel.lower().replace("-", "_")
        if key in ("none", "l2", "trivial"):
            return None
        if key in _KERNELS:
            return _KERNELS[key]() if width is None else _KERNELS[key](width)
        raise ValueError(f"unknown robust kernel {kernel!r}; expected one of {sorted(_KERNELS)} or 'none'")
    raise TypeError(f"kernel must be None, a name or a RobustKernel, got {type(kernel).__name__}")
