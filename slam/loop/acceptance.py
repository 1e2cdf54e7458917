"""How far a loop may disagree with the current estimate: a bound that grows with the distance travelled.

The bound is affine in the distance ``L`` travelled between the two keyframes along the keyframe graph
(:meth:`KeyframeGraph.path_lengths`; ``inf`` across a tracking loss: the caps apply)::

    translation <= translation_base + translation_per_metre * L
    rotation    <= rotation_base_deg + rotation_per_metre_deg * L      (both capped)

The same bound, on the sum of the two paths, decides whether two loops agree (:func:`pairwise_consistent`).

Example:
    >>> cfg = DriftBoundConfig()
    >>> near, far = drift_limits(0.5, cfg), drift_limits(20.0, cfg)
    >>> near.translation < far.translation and near.rotation_deg < far.rotation_deg
    True
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import torch

from slam.lie import se3_between, se3_compose, so3_log
from slam.loop.verification import DriftLimits
from slam.odometry.config import check_number

Tensor = torch.Tensor

__all__ = ["DriftBoundConfig", "capped_length", "drift_limits", "drift_limits_array", "pairwise_consistent",
           "pairwise_errors"]


@dataclass(frozen=True)
class DriftBoundConfig:
    """The affine drift bound (see the module docstring)."""

    # At L = 0: the loop's own error and the estimate's local error
    translation_base: float = 0.15  # m
    rotation_base_deg: float = 8.0  # degrees
    # Growth per metre travelled: above the worst odometry drift measured per metre of path
    translation_per_metre: float = 0.05  # m / m
    rotation_per_metre_deg: float = 1.5  # deg / m
    # Caps: beyond these a "loop" says the camera is elsewhere altogether (an aliased place)
    max_translation: float = 1.5  # m
    max_rotation_deg: float = 45.0  # degrees

    def __post_init__(self) -> None:
        for f in fields(self):
            check_number("DriftBoundConfig", f.name, getattr(self, f.name), 0, finite=True)


def drift_limits_array(path_length, config: DriftBoundConfig) -> tuple[np.ndarray, np.ndarray]:
    """:func:`drift_limits` of many path lengths at once: (translations m, rotations deg), each ``(k,)``.

    Args:
        path_length: ``(k,)`` metres (``inf``: the caps).
        config: :class:`DriftBoundConfig`.
    """
    L = np.asarray(path_length, dtype=np.float64)
    if not bool(np.all(L >= 0)):
        raise ValueError(f"path_length must be >= 0, got {L[~(L >= 0)][:3].tolist()}")
    finite = np.isfinite(L)
    Lf = np.where(finite, L, 0.0)
    t = np.where(finite, np.minimum(config.translation_base + config.translation_per_metre * Lf,
                                    config.max_translation), config.max_translation)
    r = np.where(finite, np.minimum(config.rotation_base_deg + config.rotation_per_metre_deg * Lf,
                                    config.max_rotation_deg), config.max_rotation_deg)
    return t, r


def drift_limits(path_length: float, config: DriftBoundConfig) -> DriftLimits:
    """The allowed disagreement after ``path_length`` metres travelled between two keyframes.

    Args:
        path_length: metres (``inf`` when no measured path joins the keyframes: the caps apply).
        config: :class:`DriftBoundConfig`.
    """
    t, r = drift_limits_array([float(path_length)], config)
    return DriftLimits(float(t[0]), float(r[0]))


def capped_length(config: DriftBoundConfig) -> float:
    """The path length from which both bounds are at their caps (``inf`` when one never reaches its cap)."""
    def reach(base: float, rate: float, cap: float) -> float:
        if base >= cap:
            return 0.0
        return (cap - base) / rate if rate > 0 else math.inf

    return max(reach(config.translation_base, config.translation_per_metre, config.max_translation),
               reach(config.rotation_base_deg, config.rotation_per_metre_deg, config.max_rotation_deg))


def pairwise_consistent(T_a1b1: Tensor, T_a2b2: Tensor, T_a1a2: Tensor, T_b1b2: Tensor,
                        limits: DriftLimits) -> tuple[bool, float, float]:
    """Whether two loops ``a1 -> b1`` and ``a2 -> b2`` agree, given the estimate between their ends.

    The cycle ``a1 -> b1 -> b2 -> a2 -> a1`` must come back to the start: its error is
    ``(T_a1a2 T_a2b2)^-1 T_a1b1 T_b1b2``.

    Args:
        T_a1b1, T_a2b2: ``(7,)`` the loops' measured relative poses.
        T_a1a2, T_b1b2: ``(7,)`` the estimate's relative poses between their ends.
        limits: the allowed cycle error (e.g. :func:`drift_limits` of the two paths' total length).

    Returns:
        (consistent, translation error m, rotation error deg).
    """
    dt, dr = pairwise_errors(T_a1b1, T_a2b2, T_a1a2, T_b1b2)
    dt, dr = float(dt), float(dr)
    return (dt <= limits.translation and dr <= limits.rotation_deg), dt, dr


def pairwise_errors(T_a1b1: Tensor, T_a2b2: Tensor, T_a1a2: Tensor, T_b1b2: Tensor) -> tuple[Tensor, Tensor]:
    """The cycle error of :func:`pairwise_consistent` for a batch of loop pairs (broadcasting).

    Args:
        T_a1b1, T_a2b2: ``(..., 7)`` the loops' measured relative poses.
        T_a1a2, T_b1b2: ``(..., 7)`` the estimate's relative poses between their ends.

    Returns:
        (translation errors m, rotation errors deg), each ``(...)`` float64 tensors.
    """
    err = se3_between(se3_compose(T_a1a2, T_a2b2), se3_compose(T_a1b1, T_b1b2))
    return err[..., :3].norm(dim=-1), so3_log(err[..., 3:]).norm(dim=-1) * (180.0 / math.pi)  # as math.degrees
