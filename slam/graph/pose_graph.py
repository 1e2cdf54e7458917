"""The pose graph: poses, edges as index tensors, relative-pose measurements and their information.

Convention (as in g2o and GTSAM): an edge ``(i, j)`` measures ``z_ij ~= T_i^-1 T_j``, the pose of ``j``
in the frame of ``i``; poses are ``(N, 7) = [t, q_xyzw]`` (``T_i`` maps frame ``i`` to the world).
Its information ``Omega_ij (6, 6)`` weighs the residual ``r_ij`` in the tangent order ``[rho, phi]``
(translation first), see :mod:`slam.graph.costs`.

Example:
    >>> import torch
    >>> from slam.lie import se3_exp
    >>> g = PoseGraph.from_lists([se3_exp(torch.zeros(6, dtype=torch.float64))] * 3,
    ...                          [(0, 1, se3_exp(torch.tensor([1.0, 0, 0, 0, 0, 0], dtype=torch.float64)))])
    >>> g.add_edge(1, 2, g.measurements[0])
    >>> g.poses.shape, g.ii.tolist(), g.jj.tolist(), g.information.shape
    (torch.Size([3, 7]), [0, 1], [1, 2], torch.Size([2, 6, 6]))
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np
import torch

from slam.lie import se3_normalize

__all__ = ["CHARTS", "SYMMETRY_RTOL", "PoseGraph", "require_spd_information"]

SYMMETRY_RTOL = 1e-6  # an information matrix is symmetric when |A - A^T| <= this * its largest diagonal entry

Tensor = torch.Tensor

# the residual charts of slam.graph.costs
CHARTS = ("se3", "r3so3")


def _as_tensor(x, dtype, device, name: str) -> Tensor:
    if isinstance(x, Tensor):
        return x.to(dtype=dtype, device=device)
    try:
        return torch.as_tensor(x, dtype=dtype, device=device)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be a tensor or convertible to one: {exc}") from None


@dataclass
class PoseGraph:
    """A graph of ``N`` poses and ``E`` relative-pose edges, checked on construction (a ``ValueError`` names the
    field, the edge and what was expected).

    Attributes:
        poses: ``(N, 7)`` ``[t, q_xyzw]`` current estimate (the optimiser's initial guess).
        ii: ``(E,)`` long, the first pose of each edge.
        jj: ``(E,)`` long, the second pose of each edge.
        measurements: ``(E, 7)`` measured ``z_ij ~= T_i^-1 T_j``.
        information: ``(E, 6, 6)`` symmetric positive-definite information matrices, ``[rho, phi]`` order.
        chart: the residual chart, one of :data:`CHARTS` (default ``"se3"``).
        vertex_ids: ``(N,)`` long, the ids the poses had in the file they were read from (row ``k`` of
            ``poses`` is vertex ``vertex_ids[k]``); ``arange(N)`` for graphs built in code.
        fixed: ``(K,)`` long, sorted indices of the poses held constant by :func:`~slam.graph.optimize`
            (g2o ``FIX`` lines); empty by default.
    """

    poses: Tensor
    ii: Tensor
    jj: Tensor
    measurements: Tensor
    information: Tensor
    chart: str = "se3"
    vertex_ids: Optional[Tensor] = None
    fixed: Optional[Tensor] = None

    def __post_init__(self) -> None:
        if not isinstance(self.poses, Tensor):
            raise TypeError(f"poses must be a torch.Tensor, got {type(self.poses).__name__}")
        dtype = self.poses.dtype if self.poses.is_floating_point() else torch.float64
        dev = self.poses.device
        self.poses = self.poses.to(dtype)
        self.ii = _as_tensor(self.ii, torch.long, dev, "ii")
        self.jj = _as_tensor(self.jj, torch.long, dev, "jj")
        self.measurements = _as_tensor(self.measurements, dtype, dev, "measurements")
        self.information = _as_tensor(self.information, dtype, dev, "information")
        if self.vertex_ids is None:
            self.vertex_ids = torch.arange(self.poses.shape[0] if self.poses.dim() == 2 else 0, device=dev)
        else:
            self.vertex_ids = _as_tensor(self.vertex_ids, torch.long, dev, "vertex_ids")
        self.fixed = (torch.zeros(0, dtype=torch.long, device=dev) if self.fixed is None
                      else torch.unique(_as_tensor(self.fixed, torch.long, dev, "fixed").reshape(-1)))
        self.validate(check_information=False)

    @property
    def num_poses(self) -> int:
        return int(self.poses.shape[0])

    @property
    def num_edges(self) -> int:
        return int(self.ii.shape[0])

    @property
    def dtype(self) -> torch.dtype:
        return self.poses.dtype

    @property
    def device(self) -> torch.device:
        return self.poses.device

    def __repr__(self) -> str:
        return (f"PoseGraph(num_poses={self.num_poses}, num_edges={self.num_edges}, chart={self.chart!r}, "
                f"dtype={self.dtype})")

    def validate(self, check_information: bool = True) -> PoseGraph:
        """Check shapes, indices and values (``check_information``: also that every information matrix is
        symmetric positive definite); a ``ValueError`` names the first problem. Returns ``self``."""
        P, E = self.poses, self.ii
        if P.dim() != 2 or P.shape[-1] != 7:
            raise ValueError(f"poses must have shape (N, 7), got {tuple(P.shape)}")
        n, e = P.shape[0], E.shape[0] if E.dim() == 1 else -1
        if self.ii.dim() != 1 or self.jj.shape != self.ii.shape:
            raise ValueError(f"ii and jj must both have shape (E,), got {tuple(self.ii.shape)} and "
                             f"{tuple(self.jj.shape)}")
        if self.measurements.shape != (e, 7):
            raise ValueError(f"measurements must have shape (E, 7) = ({e}, 7), got "
                             f"{tuple(self.measurements.shape)}")
        if self.information.shape != (e, 6, 6):
            raise ValueError(f"information must have shape (E, 6, 6) = ({e}, 6, 6), got "
                             f"{tuple(self.information.shape)}")
        if self.vertex_ids.shape != (n,):
            raise ValueError(f"vertex_ids must have shape (N,) = ({n},), got {tuple(self.vertex_ids.shape)}")
        if self.fixed.dim() != 1:
            raise ValueError(f"fixed must have shape (K,), got {tuple(self.fixed.shape)}")
        bad = (self.fixed < 0) | (self.fixed >= n)
        if bool(bad.any()):
            raise ValueError(f"fixed pose index {int(self.fixed[bad][0])} is not a pose index in [0, {n})")
        if self.chart not in CHARTS:
            raise ValueError(f"chart must be one of {CHARTS}, got {self.chart!r}")
        if e:
            for name, idx in (("ii", self.ii), ("jj", self.jj)):
                bad = (idx < 0) | (idx >= n)
                if bool(bad.any()):
                    k = int(bad.nonzero()[0, 0])
                    raise ValueError(f"edge {k}: {name}[{k}] = {int(idx[k])} is not a pose index in [0, {n})")
            loop = self.ii == self.jj
            if bool(loop.any()):
                k = int(loop.nonzero()[0, 0])
                raise ValueError(f"edge {k} connects pose {int(self.ii[k])} to itself")
        for name, x in (("poses", P), ("measurements", self.measurements), ("information", self.information)):
            bad = ~torch.isfinite(x).flatten(1).all(-1)
            if bool(bad.any()):
                raise ValueError(f"{name}[{int(bad.nonzero()[0, 0])}] has a non-finite value")
        for name, x in (("poses", P), ("measurements", self.measurements)):
            qn = x[:, 3:].norm(dim=-1)
            bad = (qn - 1.0).abs() > 1e-3
            if bool(bad.any()):
                k = int(bad.nonzero()[0, 0])
                raise ValueError(f"{name}[{k}] has a quaternion of norm {float(qn[k]):.6g}, expected 1 "
                                 f"(use slam.lie.se3_normalize)")
        if check_information and e:
            require_spd_information(self.information, self.ii, self.jj)
        return self

    def add_edge(self, i: int, j: int, measurement: Tensor, information: Optional[Tensor] = None) -> None:
        """Append an edge ``z_ij ~= T_i^-1 T_j``: ``measurement (7,)``, ``information (6, 6)`` (default I)."""
        meas = torch.as_tensor(measurement, dtype=self.dtype, device=self.device).reshape(1, 7)
        self.add_edges(torch.tensor([i]), torch.tensor([j]), meas,
                       None if information is None else torch.as_tensor(information).reshape(1, 6, 6))

    def add_edges(self, ii: Tensor, jj: Tensor, measurements: Tensor,
                  information: Optional[Tensor] = None) -> None:
        """Append edges: ``ii, jj (K,)``, ``measurements (K, 7)``, ``information (K, 6, 6)`` (default ``I``),
        validated (indices, quaternions, positive-definite information) before the graph changes."""
        ii = _as_tensor(ii, torch.long, self.device, "ii").reshape(-1)
        jj = _as_tensor(jj, torch.long, self.device, "jj").reshape(-1)
        k = ii.shape[0]
        meas = _as_tensor(measurements, self.dtype, self.device, "measurements")
        if information is None:
            info = torch.eye(6, dtype=self.dtype, device=self.device).expand(k, 6, 6).clone()
        else:
            info = _as_tensor(information, self.dtype, self.device, "information")
        new = PoseGraph(self.poses, ii, jj, meas, info, self.chart, self.vertex_ids, self.fixed)
        new.validate()
        self.ii = torch.cat([self.ii, new.ii])
        self.jj = torch.cat([self.jj, new.jj])
        self.measurements = torch.cat([self.measurements, new.measurements])
        self.information = torch.cat([self.information, new.information])

    def with_poses(self, poses: Tensor, check: bool = True) -> PoseGraph:
        """A copy sharing the (already validated) edges, with other poses ``(N, 7)`` (checked to be finite
        unless ``check`` is False)."""
        if not isinstance(poses, Tensor) or poses.shape != self.poses.shape:
            raise ValueError(f"poses must have shape {tuple(self.poses.shape)}, got "
                             f"{tuple(getattr(poses, 'shape', ()))}")
        if check and not bool(torch.isfinite(poses).all()):
            raise ValueError("poses has a non-finite value")
        out = object.__new__(PoseGraph)  # skips re-validating the shared edges
        out.__dict__.update(self.__dict__)
        out.poses = poses.to(self.poses.dtype)
        return out

    def clone(self) -> PoseGraph:
        return PoseGraph(self.poses.clone(), self.ii.clone(), self.jj.clone(), self.measurements.clone(),
                         self.information.clone(), self.chart, self.vertex_ids.clone(), self.fixed.clone())

    def to(self, device=None, dtype: Optional[torch.dtype] = None) -> PoseGraph:
        """A copy on another device and/or floating dtype (indices stay long)."""
        f = {"device": device, "dtype": dtype}
        return PoseGraph(self.poses.to(**f), self.ii.to(device), self.jj.to(device),
                         self.measurements.to(**f), self.information.to(**f), self.chart,
                         self.vertex_ids.to(device), self.fixed.to(device))

    def is_planar(self, tol: float = 1e-9) -> bool:
        """True when every pose and measurement lies in the plane ``z = 0`` with a yaw-only rotation and
        no information couples (x, y, yaw) with (z, roll, pitch): then the problem splits exactly."""
        poses, meas, info = (t.detach().cpu().double().numpy() for t in
                             (self.poses, self.measurements, self.information))
        # z, qx, qy: columns 2:5 of the poses and measurements (a NaN is not planar)
        if not all((np.abs(p[:, 2:5]) <= tol).all() for p in (poses, meas)):
            return False
        scale = np.abs(info).max(axis=(1, 2))
        cross = np.abs(info[:, [0, 1, 5], 2:5])  # (x, y, yaw) coupled with (z, roll, pitch)
        return bool((cross <= tol * scale[:, None, None]).all())

    @staticmethod
    def from_lists(poses: Sequence, edges: Iterable[Tuple]) -> PoseGraph:
        """A float64 graph from ``N`` poses ``(7,)`` (tensors or sequences, or one ``(N, 7)`` tensor) and edges
        ``(i, j, measurement (7,))`` or ``(i, j, measurement, information (6, 6))``; quaternions normalised."""
        f64 = torch.float64
        if isinstance(poses, Tensor):
            P = poses.to(f64).reshape(-1, 7)
        else:
            P = (torch.stack([torch.as_tensor(p, dtype=f64).reshape(7) for p in poses]) if len(poses)
                 else torch.zeros(0, 7, dtype=f64))
        ii, jj, meas, info = [], [], [], []
        for k, e in enumerate(edges):
            if len(e) not in (3, 4):
                raise ValueError(f"edge {k} must be (i, j, measurement) or (i, j, measurement, information), "
                                 f"got a tuple of length {len(e)}")
            ii.append(int(e[0]))
            jj.append(int(e[1]))
            meas.append(torch.as_tensor(e[2], dtype=f64).reshape(7))
            info.append(torch.eye(6, dtype=f64) if len(e) == 3
                        else torch.as_tensor(e[3], dtype=f64).reshape(6, 6))
        Z = torch.stack(meas) if meas else torch.zeros(0, 7, dtype=f64)
        Om = torch.stack(info) if info else torch.zeros(0, 6, 6, dtype=f64)
        return PoseGraph(se3_normalize(P), torch.tensor(ii, dtype=torch.long), torch.tensor(jj, dtype=torch.long),
                         se3_normalize(Z), Om).validate()


def require_spd_information(information: Tensor, ii: Tensor, jj: Tensor, fail: Optional[Tensor] = None,
                            symmetry: bool = True) -> None:
    """A ``ValueError`` naming the first edge (of ``ii, jj (E,)``) whose information matrix ``(E, 6, 6)`` is not
    symmetric positive definite. ``fail``: the ``info`` of a ``torch.linalg.cholesky_ex`` of these matrices
    already made; ``symmetry=False`` skips the symmetry test (|A - A^T| <= :data:`SYMMETRY_RTOL` times the
    largest diagonal entry)."""
    if fail is None:
        _, fail = torch.linalg.cholesky_ex(information.to(torch.float64))
    bad = fail != 0
    if symmetry and not torch.equal(information, information.mT):  # exactly symmetric: g2o stores a triangle
        # the largest entry of an SPD matrix is on its diagonal (any other matrix fails the Cholesky)
        scale = information.diagonal(dim1=-2, dim2=-1).amax(-1).clamp_min(torch.finfo(information.dtype).tiny)
        bad = bad | ((information - information.mT).abs().amax(dim=(-2, -1)) > SYMMETRY_RTOL * scale)
    if bool(bad.any()):
        k = int(bad.nonzero()[0, 0])
        raise ValueError(f"information[{k}] (edge {int(ii[k])} -> {int(jj[k])}) is not symmetric positive definite")
