"""Simulated pose graphs of any size: a 3D "Manhattan world" walk with loop closures.

Graphs of any size with a known ground truth, built as the public benchmarks were: a walk on a grid, noisy
relative-pose measurements, loop closures where the walk revisits a cell, and the odometry composed from the
first pose as the initial guess.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from slam.graph.pose_graph import PoseGraph
from slam.lie import quat_mul, se3_between, se3_compose, se3_exp, se3_normalize, so3_exp

__all__ = ["SimulatedGraph", "compose_chain", "manhattan_world"]

Tensor = torch.Tensor

# the four headings of the walk (yaw 0, 90, 180, 270 degrees) as unit steps on the grid
_STEPS = np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]])
# chances of a loop edge on arriving in a visited cell, of a turn, and of a floor change at each step
_LOOP_P, _TURN_P, _LEVEL_P = 0.5, 0.3, 0.05


@dataclass
class SimulatedGraph:
    """A simulated pose graph and its ground truth.

    Attributes:
        graph: the :class:`PoseGraph`; its poses ``(N, 7)`` are the odometry composed from pose 0, its
            edges are the ``N - 1`` odometry edges ``(k, k + 1)`` followed by the loop closures.
        ground_truth: ``(N, 7)`` the true poses (pose 0 is the identity and equals the graph's).
        num_loops: the number of loop-closure edges (the other ``N - 1`` edges are odometry).
    """

    graph: PoseGraph
    ground_truth: Tensor
    num_loops: int


def compose_chain(first: Tensor, steps: Tensor) -> Tensor:
    """Poses of a chain: ``first`` followed by ``first * steps[0] * ... * steps[k]`` for every ``k``, by a
    parallel prefix product (quaternions are not re-normalised).

    Args:
        first: ``(7,)`` the first pose.
        steps: ``(K, 7)`` the relative poses, ``K >= 0``.

    Returns:
        ``(K + 1, 7)`` poses, in the dtype and on the device of ``steps``.
    """
    if not isinstance(first, Tensor) or not isinstance(steps, Tensor):
        raise TypeError(f"first and steps must be tensors, got {type(first).__name__} and {type(steps).__name__}")
    if first.shape != (7,):
        raise ValueError(f"first must have shape (7,), got {tuple(first.shape)}")
    if steps.dim() != 2 or steps.shape[-1] != 7:
        raise ValueError(f"steps must have shape (K, 7), got {tuple(steps.shape)}")
    if not steps.is_floating_point():
        raise ValueError(f"steps must be floating point, got {steps.dtype}")
    P = torch.cat([first.reshape(1, 7).to(steps), steps])
    off = 1
    while off < P.shape[0]:
        # P[k] <- P[k - off] * P[k]: after the round P[k] is the product of entries max(0, k - 2 off + 1) .. k
        P = torch.cat([P[:off], se3_compose(P[:-off], P[off:])])
        off *= 2
    return P


def _check_float(name: str, value: float) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")


def manhattan_world(num_poses: int, seed: int = 0, sigma_t: float = 0.05, sigma_r: float = 0.01,
                    tilt: float = 0.05, dtype: torch.dtype = torch.float64) -> SimulatedGraph:
    """A walk on a 3D grid with loop closures (a 3D Manhattan world, in the manner of M3500).

    Every step changes floor (two floors) or turns by 90 degrees at random and moves one metre along the
    heading, inside a square of about ``sqrt(num_poses) / 2`` cells a side. Each true pose is
    ``R = Rz(yaw) * exp([roll, pitch, 0])`` with ``roll, pitch ~ N(0, tilt^2)`` (pose 0: the identity).
    Arriving in a cell visited before (not by the previous pose) may add an edge from an earlier pose there.

    Measurements are the true ``T_i^-1 T_j`` times ``exp(n)``, ``n ~ N(0, diag(sigma_t^2 I3, sigma_r^2 I3))``
    (``[rho, phi]`` order), with the inverse covariance as information (1 where a sigma is 0, so the ground
    truth stays an exact minimum). The walk and the loop edges depend only on ``num_poses`` and ``seed``.

    Args:
        num_poses: ``N >= 2``.
        seed: seed of every random choice (same seed, same graph).
        sigma_t: translation noise (metres), ``>= 0``.
        sigma_r: rotation noise (radians), ``>= 0``.
        tilt: standard deviation of the random roll and pitch of the true poses (radians), ``>= 0``.
        dtype: floating dtype of the graph and the ground truth (everything is computed in float64).

    Returns:
        A :class:`SimulatedGraph`: ``graph.poses (N, 7)``, ``graph.ii, graph.jj (E,)``,
        ``graph.measurements (E, 7)``, ``graph.information (E, 6, 6)`` with ``E = N - 1 + num_loops``, and
        ``ground_truth (N, 7)``.

    Raises:
        ValueError: ``num_poses < 2``, a negative or non-finite sigma or tilt, or a non-floating ``dtype``.
    """
    if isinstance(num_poses, bool) or not isinstance(num_poses, (int, np.integer)) or num_poses < 2:
        raise ValueError(f"num_poses must be an integer >= 2, got {num_poses!r}")
    for name, value in (("sigma_t", sigma_t), ("sigma_r", sigma_r), ("tilt", tilt)):
        _check_float(name, value)
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise ValueError(f"dtype must be a floating torch dtype, got {dtype!r}")
    num_poses = int(num_poses)
    rng = np.random.default_rng(seed)
    half = max(2, int(np.sqrt(num_poses) / 4))  # square of 2 * half + 1 cells a side
    cell = np.zeros(3, dtype=np.int64)
    heading = 0
    cells = np.empty((num_poses, 3), dtype=np.int64)
    yaw = np.empty(num_poses)
    visits: dict[tuple, list[int]] = {}
    loops_i: list[int] = []
    loops_j: list[int] = []
    for k in range(num_poses):
        if k:
            if rng.random() < _LEVEL_P:
                cell = cell + np.array([0, 0, 1 if cell[2] <= 0 else -1])
            else:
                if rng.random() < _TURN_P:
                    heading = (heading + (1 if rng.random() < 0.5 else 3)) % 4
                for _ in range(4):  # turn until the step stays in the square (one of 4 headings always does)
                    nxt = cell + _STEPS[heading]
                    if np.abs(nxt[:2]).max() <= half:
                        break
                    heading = (heading + 1) % 4
                cell = nxt
        key = tuple(cell)
        seen = visits.setdefault(key, [])
        if seen and seen[-1] != k - 1 and rng.random() < _LOOP_P:
            loops_i.append(int(seen[rng.integers(len(seen))]))
            loops_j.append(k)
        seen.append(k)
        cells[k], yaw[k] = cell, heading * np.pi / 2
    # true rotations: the heading's yaw, then a small roll and pitch about the pose's own x and y axes
    tilts = np.zeros((num_poses, 3))
    tilts[:, :2] = rng.normal(0.0, tilt, (num_poses, 2))
    tilts[0] = 0.0
    yaw_vec = np.zeros((num_poses, 3))
    yaw_vec[:, 2] = yaw
    q = quat_mul(so3_exp(torch.from_numpy(yaw_vec)), so3_exp(torch.from_numpy(tilts)))
    gt = se3_normalize(torch.cat([torch.from_numpy(cells.astype(np.float64)), q], dim=-1))
    ii = torch.cat([torch.arange(num_poses - 1), torch.tensor(loops_i, dtype=torch.long)])
    jj = torch.cat([torch.arange(1, num_poses), torch.tensor(loops_j, dtype=torch.long)])
    sigma = torch.tensor([sigma_t] * 3 + [sigma_r] * 3, dtype=torch.float64)
    # drawn even when sigma is 0 so that the same seed gives the same draws whatever the sigmas
    noise = torch.from_numpy(rng.standard_normal((ii.shape[0], 6))) * sigma
    Z = se3_normalize(se3_compose(se3_between(gt[ii], gt[jj]), se3_exp(noise)))
    weight = torch.where(sigma > 0, sigma, torch.ones_like(sigma)) ** -2
    if not bool(torch.isfinite(weight).all()):
        raise ValueError(f"sigma_t = {sigma_t!r} and sigma_r = {sigma_r!r} give an infinite information "
                         f"sigma^-2; use 0 for exact measurements")
    info = torch.diag(weight).expand(ii.shape[0], 6, 6).clone()
    init = se3_normalize(compose_chain(gt[0], Z[:num_poses - 1]))
    graph = PoseGraph(init.to(dtype), ii, jj, Z.to(dtype), info.to(dtype))
    return SimulatedGraph(graph=graph, ground_truth=gt.to(dtype), num_loops=len(loops_i))
