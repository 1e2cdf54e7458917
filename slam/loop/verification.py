"""Geometric verification of one loop candidate: register the two keyframes and decide, with the reasons.

:func:`verify_candidate` is a pure function: it returns a :class:`Verification` and changes nothing else.

Example:
    >>> import torch
    >>> from slam.config import LoopClosureConfig
    >>> from slam.odometry.features import FrameFeatures
    >>> empty = FrameFeatures(torch.zeros(0, 2), torch.zeros(0, 32, dtype=torch.uint8), torch.zeros(0, 3),
    ...                       torch.zeros(0, dtype=torch.bool), torch.zeros(0), torch.eye(3, dtype=torch.float64),
    ...                       (480, 640))
    >>> v = verify_candidate(empty, empty, torch.tensor([0, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64),
    ...                      DriftLimits(0.3, 20.0), LoopClosureConfig())
    >>> v.accepted, v.reason.startswith("registration failed")
    (False, True)
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import torch

from slam.lie import quat_angle, se3_between, se3_identity
from slam.odometry.features import FrameFeatures
from slam.odometry.registration import register

Tensor = torch.Tensor

__all__ = ["DriftLimits", "Verification", "verify_candidate"]


class DriftLimits(NamedTuple):
    """How far a loop's measured relative pose may disagree with the current estimate of it.

    Attributes:
        translation: metres.
        rotation_deg: degrees.
    """

    translation: float
    rotation_deg: float


@dataclass
class Verification:
    """The outcome of :func:`verify_candidate` for keyframes ``a`` (older) and ``b`` (the query).

    Attributes:
        accepted: every check passed.
        reason: why not ("" when accepted).
        T_ab: ``(7,)`` float64 measured pose of b in a (identity when the registration failed or was
            not tried).
        information: ``(6, 6)`` float64 information of ``T_ab`` from the registration (unscaled).
        num_matches, num_inliers: of the registration.
        distance, rotation_deg: size of the measured relative pose.
        disagreement, disagreement_deg: between ``T_ab`` and the current estimate of it (NaN when not
            reached).
        limits: the :class:`DriftLimits` it was held to.
    """

    accepted: bool
    reason: str
    T_ab: Tensor
    information: Tensor
    num_matches: int = 0
    num_inliers: int = 0
    distance: float = math.nan
    rotation_deg: float = math.nan
    disagreement: float = math.nan
    disagreement_deg: float = math.nan
    limits: DriftLimits = DriftLimits(math.nan, math.nan)


def _rotation_deg(q: Tensor) -> float:
    return math.degrees(float(quat_angle(q)))


def verify_candidate(a: FrameFeatures, b: FrameFeatures, estimate_ab: Tensor, limits: DriftLimits,
                     config) -> Verification:
    """Register keyframe b against keyframe a and check the result.

    Checks, in order: the registration succeeds; enough inliers and inlier ratio; the views are close
    (``config.max_translation`` / ``max_rotation_deg``); the measurement agrees with ``estimate_ab`` within
    ``limits``. An estimate farther than the last two allow together is refused before registering.

    Args:
        a: features of the older keyframe.
        b: features of the query keyframe.
        estimate_ab: ``(7,)`` the current estimate of the pose of b in a (odometry, or corrected by loops).
        limits: the allowed disagreement (see :mod:`slam.loop.acceptance`).
        config: :class:`slam.config.LoopClosureConfig`.

    Returns:
        :class:`Verification`.
    """
    if estimate_ab.shape != (7,):
        raise ValueError(f"estimate_ab must have shape (7,), got {tuple(estimate_ab.shape)}")
    est = estimate_ab.to(torch.float64).cpu()
    reach, reach_deg = config.max_translation + limits.translation, config.max_rotation_deg + limits.rotation_deg
    dist, turn = float(est[:3].norm()), _rotation_deg(est[3:])
    if dist > reach + 1e-6 or turn > reach_deg + 1e-6:  # the margin: rounding never refuses what would pass
        reason = (f"contradicts the estimate: it puts the views {dist:.2f} m / {turn:.0f} deg apart, beyond "
                  f"{reach:.2f} m / {reach_deg:.0f} deg (views too far apart plus the bound)")
        return Verification(False, reason, se3_identity(dtype=torch.float64),
                            torch.zeros(6, 6, dtype=torch.float64), limits=limits)
    res = register(a, b, config.registration)
    T_ab = res.T_ab.detach().to(torch.float64).cpu()
    info = res.information.detach().to(torch.float64).cpu()
    out = Verification(False, "", T_ab, info, res.num_matches, res.num_inliers, limits=limits)
    if not res.success:
        return replace(out, reason=f"registration failed: {res.reason}")
    if res.num_inliers < config.min_inliers:
        return replace(out, reason=f"{res.num_inliers} inliers < {config.min_inliers}")
    ratio = res.num_inliers / max(res.num_matches, 1)
    if ratio < config.min_inlier_ratio:
        return replace(out, reason=f"inlier ratio {ratio:.2f} < {config.min_inlier_ratio}")
    out.distance, out.rotation_deg = float(T_ab[:3].norm()), _rotation_deg(T_ab[3:])
    if out.distance > config.max_translation or out.rotation_deg > config.max_rotation_deg:
        return replace(out, reason=f"views too far apart ({out.distance:.2f} m, {out.rotation_deg:.0f} deg)")
    diff = se3_between(est, T_ab)
    out.disagreement, out.disagreement_deg = float(diff[:3].norm()), _rotation_deg(diff[3:])
    if out.disagreement > limits.translation or out.disagreement_deg > limits.rotation_deg:
        return replace(out, reason=f"contradicts the estimate by {out.disagreement:.2f} m / {out.disagreement_deg:.0f} "
                                   f"deg (bound {limits.translation:.2f} m / {limits.rotation_deg:.0f} deg)")
    return replace(out, accepted=True)
