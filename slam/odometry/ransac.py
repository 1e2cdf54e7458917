"""3D-3D RANSAC for a rigid transform, vectorised over hypotheses, with a refinement on the inliers.

1. Hypotheses: batches of random 3-point samples (seeded ``torch.Generator``), samples with a tiny
   triangle or whose pairwise distances are not preserved (a rigid motion keeps them) are discarded,
   each remaining one is fitted with :func:`~slam.odometry.geometry.kabsch` (batched SVD) and scored on
   all correspondences at once with the MSAC truncated quadratic cost. The number of batches adapts to
   the best inlier ratio ``w``: ``log(1 - confidence) / log(1 - w^3)`` hypotheses.
2. Local optimisation: weighted Kabsch on the inliers, inliers re-selected, fitted again.
3. Refinement: Gauss-Newton with a Huber kernel on the Mahalanobis 3D error
   ``r_i = T src_i - dst_i``, ``Sigma_i = R Sigma_src,i R^T + Sigma_dst,i`` (depth noise along the ray,
   pixel noise across: see :func:`~slam.odometry.geometry.point_covariance`), right perturbation
   ``T exp(xi)``. Its Hessian at the optimum is the returned information matrix.

Example:
    >>> g = torch.Generator().manual_seed(0)
    >>> src = torch.rand(50, 3, generator=g, dtype=torch.float64) + torch.tensor([0., 0., 1.], dtype=torch.float64)
    >>> pose = torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    >>> res = ransac_rigid(src, src + pose[:3])
    >>> res.success, res.num_inliers, res.pose.shape
    (True, 50, torch.Size([7]))
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from slam.lie import quat_to_rotmat, se3_compose, se3_exp, se3_identity
from slam.odometry.config import RansacConfig
from slam.odometry.geometry import check_shape, kabsch, rigid_jacobian, transform_points

Tensor = torch.Tensor

__all__ = ["RansacResult", "ransac_rigid", "refine_rigid"]


@dataclass
class RansacResult:
    """Outcome of :func:`ransac_rigid`.

    Attributes:
        pose: ``(7,)`` float64 transform mapping source points into the destination frame (identity on failure).
        inliers: ``(N,)`` bool.
        num_inliers: number of inliers.
        rmse: root-mean-square 3D error of the inliers (metres; ``inf`` on failure).
        information: ``(6, 6)`` float64 information of ``pose`` (right perturbation, ``[rho, phi]``; zeros on failure).
        success: whether a trustworthy transform was found.
        reason: why it failed ("" on success).
        iterations: hypotheses drawn.
    """

    pose: Tensor
    inliers: Tensor
    num_inliers: int
    rmse: float
    information: Tensor
    success: bool
    reason: str = ""
    iterations: int = 0


def _failure(n: int, reason: str, device, iterations: int = 0, inliers: Tensor | None = None,
             pose: Tensor | None = None) -> RansacResult:
    return RansacResult(
        pose=se3_identity(dtype=torch.float64, device=device) if pose is None else pose,
        inliers=torch.zeros(n, dtype=torch.bool, device=device) if inliers is None else inliers,
        num_inliers=0 if inliers is None else int(inliers.sum()), rmse=math.inf,
        information=torch.zeros(6, 6, dtype=torch.float64, device=device), success=False, reason=reason,
        iterations=iterations)


def _errors(pose: Tensor, src: Tensor, dst: Tensor) -> Tensor:
    """``|T src - dst|`` for every correspondence, ``(..., N)``."""
    return (transform_points(pose, src) - dst).norm(dim=-1)


def refine_rigid(pose: Tensor, src: Tensor, dst: Tensor, cov_src: Tensor, cov_dst: Tensor,
                 iterations: int = 5, huber_delta: float = 2.0):
    """Gauss-Newton refinement of a rigid transform on the Mahalanobis 3D error (Huber kernel).

    Args:
        pose: ``(7,)`` initial transform ``src -> dst``.
        src: ``(N, 3)`` source points; ``dst``: ``(N, 3)`` destination points.
        cov_src: ``(N, 3, 3)`` covariances of the source points (source frame); ``cov_dst`` likewise.
        iterations: Gauss-Newton steps (stops early once the step is below 1e-10).
        huber_delta: Huber threshold on the Mahalanobis distance (in sigmas).

    Returns:
        the refined ``(7,)`` pose and the ``(6, 6)`` information (Gauss-Newton Hessian without the robust
        weights) at it, for the right perturbation ``pose * exp(xi)``.
    """
    check_shape(pose, (7,), "pose")
    if src.dim() != 2 or src.shape[-1] != 3 or src.shape != dst.shape:
        raise ValueError(f"src and dst must both have shape (N, 3), got {tuple(src.shape)} and "
                         f"{tuple(dst.shape)}")
    check_shape(cov_src, (src.shape[0], 3, 3), "cov_src")
    check_shape(cov_dst, (src.shape[0], 3, 3), "cov_dst")
    J = rigid_jacobian(src)  # (N, 3, 6), d(T exp(xi) p)
    R0 = quat_to_rotmat(pose[3:])
    # residual covariance in the source frame, S_src + R^T S_dst R, at the initial rotation only (the
    # refinement turns by a fraction of a degree): J^T W J and J^T W are computed once
    W = torch.linalg.inv(cov_src + R0.transpose(0, 1) @ cov_dst @ R0)  # (N, 3, 3)
    JtW = J.transpose(1, 2) @ W  # (N, 6, 3)
    JtWJ = JtW @ J  # (N, 6, 6)
    for _ in range(iterations):
        R = quat_to_rotmat(pose[3:])
        r = (src @ R.transpose(0, 1) + pose[:3] - dst) @ R  # R^T r: the residual in the source frame
        m = torch.sqrt(((W @ r[..., None])[..., 0] * r).sum(-1).clamp_min(0))  # Mahalanobis distance
        w = torch.where(m <= huber_delta, torch.ones_like(m), huber_delta / m.clamp_min(1e-12))
        H = (JtWJ * w[:, None, None]).sum(0)
        g = ((JtW @ r[..., None])[..., 0] * w[:, None]).sum(0)
        xi, info = torch.linalg.solve_ex(H, -g)
        if int(info) != 0 or not bool(torch.isfinite(xi).all()):
            break  # singular system: keep the current pose
        pose = se3_compose(pose, se3_exp(xi))
        if float(xi.abs().max()) < 1e-10:
            break
    H = JtWJ.sum(0)
    return pose, 0.5 * (H + H.transpose(0, 1))


def ransac_rigid(src: Tensor, dst: Tensor, config: RansacConfig | None = None,
                 thresholds: Tensor | None = None, cov_src: Tensor | None = None,
                 cov_dst: Tensor | None = None) -> RansacResult:
    """Robust rigid transform between two sets of corresponding 3D points.

    Args:
        src: ``(N, 3)`` source points.
        dst: ``(N, 3)`` destination points (``dst_i ~ T src_i`` for inliers).
        config: RANSAC settings (default :class:`~slam.odometry.config.RansacConfig`).
        thresholds: optional ``(N,)`` inlier thresholds in metres (default ``config.inlier_threshold``).
        cov_src: optional ``(N, 3, 3)`` point covariances for the refinement (default isotropic with
            ``sigma = threshold / 3``); ``cov_dst`` likewise.

    Returns:
        :class:`RansacResult` in float64; ``success=False`` with a reason (never an exception) for too few
        correspondences or inliers, or (nearly) collinear inliers.

    Raises:
        ValueError: when the shapes are wrong, or a threshold is not > 0 (or NaN).
    """
    config = config or RansacConfig()
    if src.dim() != 2 or src.shape[-1] != 3 or src.shape != dst.shape:
        raise ValueError(f"src and dst must both have shape (N, 3), got {tuple(src.shape)} and "
                         f"{tuple(dst.shape)}")
    n = src.shape[0]
    device = src.device
    src = src.to(torch.float64)
    dst = dst.to(torch.float64)
    if thresholds is None:
        thresholds = torch.full((n,), config.inlier_threshold, dtype=torch.float64, device=device)
    else:
        check_shape(thresholds, (n,), "thresholds")
    thresholds = thresholds.to(torch.float64)
    if n and not bool((thresholds > 0).all()):
        # 0 divides the MSAC cost by zero, NaN or negative ones reject everything; inf is allowed
        raise ValueError("thresholds must be > 0 (metres, not NaN), got min "
                         f"{float(thresholds.min())} and max {float(thresholds.max())}")
    for name, cov in (("cov_src", cov_src), ("cov_dst", cov_dst)):
        if cov is not None:
            check_shape(cov, (n, 3, 3), name)
    if n < max(3, config.min_inliers):
        return _failure(n, f"too few correspondences ({n} < {max(3, config.min_inliers)})", device)
    if not (torch.isfinite(src).all() and torch.isfinite(dst).all()):
        return _failure(n, "non-finite points", device)

    gen = torch.Generator(device=device).manual_seed(config.seed)
    thr2 = thresholds ** 2
    best_cost = math.inf
    best_pose = se3_identity(dtype=torch.float64, device=device)
    best_count = 0
    needed = config.max_iterations
    drawn = 0
    valid_samples = 0
    log_fail = math.log(max(1.0 - config.confidence, 1e-12))
    while drawn < min(needed, config.max_iterations) or drawn < config.min_iterations:
        B = config.batch_size
        idx = torch.randint(0, n, (B, 3), generator=gen, device=device)
        S, D = src[idx], dst[idx]  # (B, 3, 3)
        area = 0.5 * torch.linalg.cross(S[:, 1] - S[:, 0], S[:, 2] - S[:, 0]).norm(dim=-1)
        # a rigid motion preserves the three pairwise distances (up to the noise of both ends)
        pairs = ([0, 1, 2], [1, 2, 0])
        ds = (S[:, pairs[0]] - S[:, pairs[1]]).norm(dim=-1)
        dd = (D[:, pairs[0]] - D[:, pairs[1]]).norm(dim=-1)
        tol = 2.0 * (thresholds[idx[:, pairs[0]]] + thresholds[idx[:, pairs[1]]])
        ok = (area > config.min_sample_area) & ((ds - dd).abs() < tol).all(dim=1)
        drawn += B
        n_ok = int(ok.sum())
        valid_samples += n_ok
        if n_ok == 0:
            continue
        poses = kabsch(S[ok], D[ok])  # (B', 7)
        e2 = ((transform_points(poses, src[None]) - dst[None]) ** 2).sum(-1)  # (B', N)
        cost = torch.minimum(e2 / thr2, torch.ones_like(e2)).sum(dim=1)  # MSAC
        k = int(torch.argmin(cost))
        if float(cost[k]) < best_cost:
            best_cost = float(cost[k])
            best_pose = poses[k]
            best_count = int((e2[k] < thr2).sum())
            w = best_count / n
            denom = math.log(max(1.0 - w ** 3, 1e-12))
            needed = math.ceil(log_fail / denom) if denom < 0 else config.max_iterations
    if valid_samples == 0:
        return _failure(n, f"degenerate: all {drawn} sampled triplets (nearly) collinear or not rigidly "
                        f"consistent", device, drawn)
    if best_count < config.min_inliers:
        return _failure(n, f"too few inliers ({best_count} < {config.min_inliers}) after {drawn} hypotheses",
                        device, drawn)

    # local optimisation: weighted refit on the inliers, re-select, refit
    pose = best_pose
    inl = _errors(pose, src, dst) < thresholds
    for _ in range(2):
        if int(inl.sum()) < 3:
            break
        pose = kabsch(src[inl], dst[inl], 1.0 / thr2[inl])
        inl = _errors(pose, src, dst) < thresholds
    count = int(inl.sum())
    if count < config.min_inliers:
        return _failure(n, f"too few inliers after refit ({count} < {config.min_inliers})", device, drawn)
    centred = src[inl] - src[inl].mean(dim=0)
    spread = torch.linalg.svdvals(centred) / math.sqrt(count)
    if float(spread[1]) < config.min_spread:
        return _failure(n, f"degenerate: inliers (nearly) collinear (2nd spread {float(spread[1]):.4f} m "
                        f"< {config.min_spread} m)", device, drawn, inliers=inl, pose=pose)

    if cov_src is None or cov_dst is None:
        iso = (thr2 / 9.0)[:, None, None] * torch.eye(3, dtype=torch.float64, device=device)
        cov_src = 0.5 * iso if cov_src is None else cov_src
        cov_dst = 0.5 * iso if cov_dst is None else cov_dst
    cov_src = cov_src.to(torch.float64)
    cov_dst = cov_dst.to(torch.float64)
    if config.refine_iterations > 0:
        pose, _ = refine_rigid(pose, src[inl], dst[inl], cov_src[inl], cov_dst[inl],
                               config.refine_iterations, config.huber_delta)
        inl = _errors(pose, src, dst) < thresholds
        count = int(inl.sum())
        if count < config.min_inliers:
            return _failure(n, f"too few inliers after refinement ({count} < {config.min_inliers})", device,
                            drawn, inliers=inl, pose=pose)
    pose, info = refine_rigid(pose, src[inl], dst[inl], cov_src[inl], cov_dst[inl], 0)
    err = _errors(pose, src[inl], dst[inl])
    rmse = float(torch.sqrt((err ** 2).mean()))
    return RansacResult(pose=pose, inliers=inl, num_inliers=count, rmse=rmse, information=info,
                        success=True, reason="", iterations=drawn)
