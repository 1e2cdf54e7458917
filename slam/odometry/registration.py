"""Two-frame RGB-D registration: match features, 3D-3D RANSAC, refine, decide.

The core of the odometry front end and the loop closure's geometric verification: ``register(fa, fb)`` returns
``T_ab``, the pose of frame ``b`` in frame ``a``, with its information (a g2o / GTSAM between-edge ``i=a, j=b``).

Example:
    >>> from slam.odometry.features import FrameFeatures
    >>> empty = FrameFeatures(torch.zeros(0, 2), torch.zeros(0, 32, dtype=torch.uint8), torch.zeros(0, 3),
    ...                       torch.zeros(0, dtype=torch.bool), torch.zeros(0), torch.eye(3, dtype=torch.float64),
    ...                       (480, 640))
    >>> res = register(empty, empty)
    >>> res.success, res.T_ab.shape, res.information.shape
    (False, torch.Size([7]), torch.Size([6, 6]))
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import torch

from slam.lie import se3_identity
from slam.odometry.config import RegistrationConfig
from slam.odometry.features import FrameFeatures
from slam.odometry.geometry import depth_sigma, point_covariance
from slam.odometry.matching import match_features
from slam.odometry.ransac import ransac_rigid

Tensor = torch.Tensor

__all__ = ["RegistrationResult", "register"]


@dataclass
class RegistrationResult:
    """Outcome of :func:`register`.

    Attributes:
        T_ab: ``(7,)`` float64 pose of frame b in frame a (``p_a = T_ab p_b``); identity on failure.
        num_matches: descriptor matches between keypoints with depth.
        num_inliers: RANSAC inliers after refinement.
        inlier_rmse: 3D RMSE of the inliers (metres; ``inf`` on failure).
        information: ``(6, 6)`` float64 information of ``T_ab`` (right perturbation, ``[rho, phi]``).
        success: whether ``T_ab`` is trustworthy.
        reason: why not ("" on success).
        matches: ``(K, 2)`` int64 indices ``(i_a, i_b)`` of the matches into the two feature sets.
        inliers: ``(K,)`` bool inlier flag of each match.
        seconds: wall time spent per stage (``"matching"``, ``"ransac"``), for profiling.
    """

    T_ab: Tensor
    num_matches: int
    num_inliers: int
    inlier_rmse: float
    information: Tensor
    success: bool
    reason: str
    matches: Tensor
    inliers: Tensor
    seconds: dict[str, float] = field(default_factory=dict)


def _fail(reason: str, device, matches: Tensor | None = None, inliers: Tensor | None = None,
          T_ab: Tensor | None = None, num_inliers: int = 0, rmse: float = float("inf")):
    matches = torch.zeros(0, 2, dtype=torch.long, device=device) if matches is None else matches
    inliers = torch.zeros(matches.shape[0], dtype=torch.bool, device=device) if inliers is None else inliers
    return RegistrationResult(
        T_ab=se3_identity(dtype=torch.float64, device=device) if T_ab is None else T_ab,
        num_matches=int(matches.shape[0]), num_inliers=num_inliers, inlier_rmse=rmse,
        information=torch.zeros(6, 6, dtype=torch.float64, device=device), success=False, reason=reason,
        matches=matches, inliers=inliers)


def _register_once(fa: FrameFeatures, fb: FrameFeatures, config: RegistrationConfig,
                   prior_ab: Tensor | None) -> RegistrationResult:
    t0 = time.perf_counter()
    matches, _ = match_features(fa, fb, config.matching, prior_ab=prior_ab)
    t1 = time.perf_counter()
    res = _verify(fa, fb, matches, config)
    res.seconds = {"matching": t1 - t0, "ransac": time.perf_counter() - t1}
    return res


def _verify(fa: FrameFeatures, fb: FrameFeatures, matches: Tensor,
            config: RegistrationConfig) -> RegistrationResult:
    device = fa.points.device
    if matches.shape[0] < config.min_matches:
        return _fail(f"too few matches ({matches.shape[0]} < {config.min_matches})", device, matches)
    pa = fa.points[matches[:, 0]].to(torch.float64)
    pb = fb.points[matches[:, 1]].to(torch.float64)
    sa = depth_sigma(pa[:, 2], config.depth_sigma_a, config.depth_sigma_b, config.depth_sigma_c)
    sb = depth_sigma(pb[:, 2], config.depth_sigma_a, config.depth_sigma_b, config.depth_sigma_c)
    rc = config.ransac
    thresholds = torch.clamp(rc.inlier_sigmas * torch.sqrt(sa ** 2 + sb ** 2), min=rc.inlier_threshold)
    Ka, Kb = fa.K.to(torch.float64), fb.K.to(torch.float64)
    cov_a = point_covariance(pa, sa, fa.sigma_px[matches[:, 0]].to(torch.float64), float(Ka[0, 0]),
                             float(Ka[1, 1]))
    cov_b = point_covariance(pb, sb, fb.sigma_px[matches[:, 1]].to(torch.float64), float(Kb[0, 0]),
                             float(Kb[1, 1]))
    # p_a = T_ab p_b: b is the source, a the destination
    res = ransac_rigid(pb, pa, rc, thresholds=thresholds, cov_src=cov_b, cov_dst=cov_a)
    if not res.success:
        return _fail(res.reason, device, matches, res.inliers, res.pose, res.num_inliers)
    if res.num_inliers < config.min_inliers:
        return _fail(f"too few inliers ({res.num_inliers} < {config.min_inliers})", device, matches,
                     res.inliers, res.pose, res.num_inliers, res.rmse)
    if res.rmse > config.max_rmse:
        return _fail(f"inlier rmse too large ({res.rmse:.3f} m > {config.max_rmse} m)", device, matches,
                     res.inliers, res.pose, res.num_inliers, res.rmse)
    return RegistrationResult(T_ab=res.pose, num_matches=int(matches.shape[0]), num_inliers=res.num_inliers,
                              inlier_rmse=res.rmse, information=res.information, success=True, reason="",
                              matches=matches, inliers=res.inliers)


def register(feats_a: FrameFeatures, feats_b: FrameFeatures, config: RegistrationConfig | None = None,
             prior_ab: Tensor | None = None) -> RegistrationResult:
    """Estimate the pose of frame b in frame a from their features.

    Args:
        feats_a: features of frame a (e.g. the keyframe, or the loop candidate).
        feats_b: features of frame b (e.g. the current frame, or the query keyframe).
        config: settings (default :class:`~slam.odometry.config.RegistrationConfig`).
        prior_ab: optional ``(7,)`` predicted ``T_ab`` used for guided matching; when the guided attempt
            fails, an unguided one follows (a wrong prior must not lose the track).

    Returns:
        :class:`RegistrationResult`; failures (no depth, too few matches or inliers, degenerate geometry,
        large residual) are reported with ``success=False`` and a reason, never raised.
    """
    config = config or RegistrationConfig()
    device = feats_a.points.device
    na, nb = feats_a.num_valid, feats_b.num_valid
    if min(na, nb) < config.min_matches:
        return _fail(f"too few keypoints with valid depth (a: {na}, b: {nb}; need {config.min_matches})",
                     device)
    if prior_ab is not None:
        guided = _register_once(feats_a, feats_b, config, prior_ab)
        if guided.success:
            return guided
        res = _register_once(feats_a, feats_b, config, None)
        res.seconds = {k: v + res.seconds.get(k, 0.0) for k, v in guided.seconds.items()}
        return res
    return _register_once(feats_a, feats_b, config, None)
