"""Simulated pose graphs of any size: a 3D "Manhattan world" walk with loop closures.

The public g2o benchmarks stop at a few thousand poses (sphere2500, M3500, parking-garage); SLAM runs
produce tens of thousands. :func:`manhattan_world` makes graphs of that size with a known ground truth,
built the way those benchmarks were: a walk on a grid, noisy relative-pose measurements, loop closures
where the walk revisits a cell, and the odometry composed from the first pose as the initial guess
(what ``gtsam.readG2o`` and the sphere2500 / M3500 files give as the starting point).

Example:
    >>> sim = manhattan_world(200, seed=0)
    >>> sim.graph.poses.shape, sim.ground_truth.shape, sim.num_loops > 0
    (torch.Size([200, 7]), torch.Size([200, 7]), True)
    >>> sim.graph.num_edges == 199 + sim.num_loops
    True
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
    """Poses of a chain: ``first`` followed by ``first * steps[0] * ... * steps[k]`` for every ``k``.

    A parallel prefix product (Hillis-Steele: ``ceil(log2(K + 1))`` batched compositions instead of ``K``
    sequential ones). Composition is associative, so the result equals the sequential product up to
    rounding; quaternions are not re-normalised (as in a sequential loop of ``se3_compose``).

    Args:
        first: ``(7,)`` the first pose.
        steps: ``(K, 7)`` the relative poses, ``K >= 0``.

    Returns:
        ``(K + 1, 7)`` poses, in the dtype and on the device of ``steps``.

    Example:
        >>> from slam.lie import se3_identity
        >>> compose_chain(se3_identity(dtype=torch.float64), se3_identity(5, dtype=torch.float64)).shape
        torch.Size([6, 7])
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
        # P[k] <- P[k - off] * P[k] (both from the previous round): the left factor is always the earlier
        # part of the chain, so after the round P[k] is the product of entries max(0, k - 2 off + 1) .. k
        P = torch.cat([P[:off], se3_compose(P[:-off], P[off:])])
        off *= 2
    return P


def _check_float(name: str, value: float, low: float, high: float = math.inf) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and low <= value <= high):
        raise ValueError(f"{name} must be a finite number in [{low}, {high}], got {value!r}")


def manhattan_world(num_poses: int, seed: int = 0, sigma_t: float = 0.05, sigma_r: float = 0.01,
                    loop_probability: float = 0.5, turn_probability: float = 0.3,
                    level_probability: float = 0.05, tilt: float = 0.05,
                    dtype: torch.dtype = torch.float64) -> SimulatedGraph:
    """A walk on a 3D grid with loop closures (a 3D Manhattan world, in the manner of M3500).

    Every step changes floor with ``level_probability`` (one metre up from ``z = 0`` or down from ``z = 1``:
    two floors, the heading kept); otherwise it turns by 90 degrees with ``turn_probability`` and moves one
    metre along the heading (a yaw of 0, 90, 180 or 270 degrees). The walk stays in a square of
    ``2 * max(2, floor(sqrt(num_poses) / 4)) + 1`` cells a side (about ``sqrt(num_poses) / 2``, so about
    ``num_poses / 2`` cells in all and each visited about twice) and turns at its border. Each true pose is
    ``R = Rz(yaw) * exp([roll, pitch, 0])`` with ``roll, pitch ~ N(0, tilt^2)`` in the pose's own frame
    (pose 0: the identity), so that the problem is fully 6-DoF. Arriving in a cell visited before (not by
    the previous pose) adds, with ``loop_probability``, an edge from a random earlier pose of that cell.

    Measurements are the true relative poses ``T_i^-1 T_j`` times ``exp(n)``,
    ``n ~ N(0, diag(sigma_t^2 I3, sigma_r^2 I3))`` in the ``[rho, phi]`` order, and the information is the
    inverse of that covariance, ``diag(sigma_t^-2 I3, sigma_r^-2 I3)``; then the residual of an edge at the
    ground truth is ``-n`` and its ``chi2`` follows a chi-square law with 6 degrees of freedom.
    A zero sigma makes those components exact; their information (infinite in theory) is then 1, so the
    ground truth stays an exact minimum (chi2 = 0 with ``sigma_t = sigma_r = 0``) and the graph stays valid.

    The random draws (walk, then tilts, then noise) come from one ``numpy`` generator seeded with ``seed``;
    the walk and the loop edges depend only on ``num_poses``, ``seed`` and the three probabilities.

    Args:
        num_poses: ``N >= 2``.
        seed: seed of every random choice (same seed, same graph).
        sigma_t: translation noise (metres), ``>= 0``.
        sigma_r: rotation noise (radians), ``>= 0``.
        loop_probability: chance of a loop edge on arriving in a visited cell.
        turn_probability: chance of a turn at each step.
        level_probability: chance of a floor change at each step (instead of a turn and a horizontal step).
        tilt: standard deviation of the random roll and pitch of the true poses (radians), ``>= 0``.
        dtype: floating dtype of the graph and the ground truth (everything is computed in float64).

    Returns:
        A :class:`SimulatedGraph`: ``graph.poses (N, 7)``, ``graph.ii, graph.jj (E,)``,
        ``graph.measurements (E, 7)``, ``graph.information (E, 6, 6)`` with ``E = N - 1 + num_loops``, and
        ``ground_truth (N, 7)``.

    Raises:
        ValueError: ``num_poses < 2``, a negative or non-finite sigma or tilt, a probability outside
            ``[0, 1]``, or a non-floating ``dtype``.
    """
    if isinstance(num_poses, bool) or not isinstance(num_poses, (int, np.integer)) or num_poses < 2:
        raise ValueError(f"num_poses must be an integer >= 2, got {num_poses!r}")
    for name, value in (("sigma_t", sigma_t), ("sigma_r", sigma_r), ("tilt", tilt)):
        _check_float(name, value, 0.0)
    for name, value in (("loop_probability", loop_probability), ("turn_probability", turn_probability),
                        ("level_probability", level_probability)):
        _check_float(name, value, 0.0, 1.0)
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
            if rng.random() < level_probability:
                cell = cell + np.array([0, 0, 1 if cell[2] <= 0 else -1])
            else:
                if rng.random() < turn_probability:
                    heading = (heading + (1 if rng.random() < 0.5 else 3)) % 4
                for _ in range(4):  # turn until the step stays in the square (one of 4 headings always does)
                    nxt = cell + _STEPS[heading]
                    if np.abs(nxt[:2]).max() <= half:
                        break
                    heading = (heading + 1) % 4
                cell = nxt
        key = tuple(cell)
        seen = visits.setdefault(key, [])
        if seen and seen[-1] != k - 1 and rng.random() < loop_probability:
            loops_i.append(int(seen[rng.integers(len(seen))]))
            loops_j.append(k)
        seen.append(k)
        cells[k], yaw[k] = cell, heading * np.pi / 2
    # true rotations: the heading's yaw, then a small roll and pitch about the pose's own x and y axes
    # (composing keeps the tilt's law the same for every heading; a single rotation vector
    # [roll, pitch, yaw] would shrink it as the yaw grows)
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
