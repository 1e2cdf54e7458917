"""Geometry of sparse RGB-D registration: back-projection, rigid fits, projection and covariances.

A pose ``(..., 7) = [t, q_xyzw]`` maps source points into the destination frame, ``p_dst = R p_src + t``;
tangent vectors are ``[rho, phi]``, right perturbation ``T exp(xi)`` as in :mod:`slam.lie`.

Example:
    >>> src = torch.tensor([[0., 0., 1.], [1., 0., 1.], [0., 1., 2.], [1., 1., 3.]], dtype=torch.float64)
    >>> pose = kabsch(src, src + torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64))
    >>> pose.shape
    torch.Size([7])
"""
from __future__ import annotations

import torch

from slam.lie import quat_to_rotmat, rotmat_to_quat, so3_hat

Tensor = torch.Tensor

__all__ = [
    "backproject",
    "check_shape",
    "depth_sigma",
    "kabsch",
    "point_covariance",
    "project",
    "rigid_jacobian",
    "transform_points",
]


def check_shape(x: Tensor, shape: tuple, name: str) -> None:
    """ValueError naming ``name`` unless the tensor ``x`` has ``shape`` (None: any size); TypeError for a non-tensor."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    ok = x.dim() == len(shape) and all(s is None or s == d for s, d in zip(shape, x.shape))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise ValueError(f"{name} must have shape {want}, got {tuple(x.shape)}")


def backproject(
    keypoints: Tensor,
    depth: Tensor,
    K: Tensor,
    min_depth: float = 0.3,
    max_depth: float = 4.0,
    window_radius: int = 1,
    max_depth_jump: float = 0.05,
) -> tuple[Tensor, Tensor]:
    """Camera-frame 3D points of keypoints from a depth image.

    A keypoint is valid when the depth at its rounded pixel lies in ``[min_depth, max_depth]`` and every
    pixel of the ``(2r+1) x (2r+1)`` window around it is valid and within ``max_depth_jump * z`` of it (no
    depth discontinuity). ``window_radius=0`` disables the window.

    Args:
        keypoints: ``(N, 2)`` pixel coordinates ``(x, y)``.
        depth: ``(H, W)`` metres, ``0`` (or NaN) where invalid.
        K: ``(3, 3)`` pinhole intrinsics.

    Returns:
        points ``(N, 3)`` in the dtype of ``depth`` (zeros where invalid) and valid ``(N,)`` bool.

    Example:
        >>> depth = torch.full((4, 5), 2.0)
        >>> K = torch.tensor([[100., 0., 2.], [0., 100., 1.5], [0., 0., 1.]])
        >>> pts, ok = backproject(torch.tensor([[2.0, 1.5], [0.0, 0.0]]), depth, K)
        >>> pts.shape, ok.tolist()
        (torch.Size([2, 3]), [True, False])
    """
    check_shape(keypoints, (None, 2), "keypoints")
    check_shape(depth, (None, None), "depth")
    check_shape(K, (3, 3), "K")
    H, W = depth.shape
    dtype = depth.dtype if depth.is_floating_point() else torch.float32
    depth = depth.to(dtype)
    kp = keypoints.to(dtype)
    kp_ok = torch.isfinite(kp).all(dim=1)
    # a NaN / inf keypoint reads pixel (0, 0) (casting it to an integer is undefined) and is invalid
    uv = torch.round(torch.where(kp_ok[:, None], kp, torch.zeros_like(kp))).long()
    x, y = uv[:, 0], uv[:, 1]
    r = int(window_radius)
    # keypoints whose window leaves the image get no point (also covers out-of-image keypoints)
    inside = kp_ok & (x >= r) & (x < W - r) & (y >= r) & (y < H - r)
    xc, yc = x.clamp(r, W - 1 - r), y.clamp(r, H - 1 - r)
    # NaN and +-inf depths are invalid (0), also with max_depth = inf or max_depth_jump = inf
    flat = torch.where(torch.isfinite(depth), depth, torch.zeros_like(depth)).reshape(-1)
    z = flat[yc * W + xc]
    # z > 0 as well: with min_depth = 0 a zero (invalid) depth must still give no point
    valid = inside & (z > 0) & (z >= min_depth) & (z <= max_depth)
    if r > 0:
        d = torch.arange(-r, r + 1, device=depth.device)
        dy, dx = torch.meshgrid(d, d, indexing="ij")
        idx = (yc[:, None] + dy.reshape(1, -1)) * W + (xc[:, None] + dx.reshape(1, -1))
        win = flat[idx]  # (N, (2r+1)^2)
        jump = (win - z[:, None]).abs().amax(dim=1)
        valid = valid & (win > 0).all(dim=1) & (jump <= max_depth_jump * z)
    Kd = K.to(dtype=dtype, device=depth.device)
    px = (kp[:, 0] - Kd[0, 2]) / Kd[0, 0] * z
    py = (kp[:, 1] - Kd[1, 2]) / Kd[1, 1] * z
    # where, not a product with the mask: NaN * 0 is NaN (a NaN keypoint must not leak into its point)
    points = torch.stack([px, py, z], dim=-1)
    points = torch.where(valid[:, None], points, torch.zeros_like(points))
    return points, valid


def depth_sigma(z: Tensor, a: float = 0.0012, b: float = 0.0019, c: float = 0.4) -> Tensor:
    """Axial depth noise (std, metres) of a Kinect v1: ``a + b (z - c)^2`` (Nguyen et al., 3DIMPVT 2012).

    Args:
        z: ``(*)`` depths in metres.

    Returns:
        ``(*)`` standard deviations.

    Example:
        >>> depth_sigma(torch.tensor([0.4, 2.4]))
        tensor([0.0012, 0.0088])
    """
    return a + b * (z - c) ** 2


def point_covariance(points: Tensor, sigma_z: Tensor, sigma_px: Tensor, fx: float, fy: float) -> Tensor:
    """Anisotropic covariance of back-projected points: depth noise along the ray, pixel noise across it.

    ``Sigma = sigma_z^2 (p/z)(p/z)^T + (sigma_px z / fx)^2 e_x e_x^T + (sigma_px z / fy)^2 e_y e_y^T``.

    Args:
        points: ``(N, 3)`` camera-frame points with ``z > 0``.
        sigma_z: ``(N,)`` depth std (metres).
        sigma_px: ``(N,)`` keypoint std (pixels).

    Returns:
        ``(N, 3, 3)`` covariances.

    Example:
        >>> point_covariance(torch.ones(5, 3), torch.ones(5), torch.ones(5), 500.0, 500.0).shape
        torch.Size([5, 3, 3])
    """
    check_shape(points, (None, 3), "points")
    ray = points / points[:, 2:3].clamp_min(1e-6)
    cov = (sigma_z ** 2)[:, None, None] * ray[:, :, None] * ray[:, None, :]
    sx = (sigma_px * points[:, 2] / fx) ** 2
    sy = (sigma_px * points[:, 2] / fy) ** 2
    cov[:, 0, 0] += sx
    cov[:, 1, 1] += sy
    return cov


def kabsch(src: Tensor, dst: Tensor, weights: Tensor | None = None) -> Tensor:
    """Weighted least-squares rigid transform (Kabsch / Umeyama without scale), batched.

    Minimises ``sum_i w_i |R src_i + t - dst_i|^2``; the reflection case is fixed by the sign of
    ``det(U V^T)``.

    Args:
        src: ``(..., N, 3)`` source points.
        dst: ``(..., N, 3)`` destination points.
        weights: ``(..., N)`` non-negative weights (default: all ones).

    Returns:
        ``(..., 7)`` poses mapping ``src`` onto ``dst``. Degenerate input (fewer than 3 non-collinear
        points) still returns a valid rotation (one of the minimisers); callers check the spread.

    Example:
        >>> kabsch(torch.randn(8, 5, 3), torch.randn(8, 5, 3)).shape
        torch.Size([8, 7])
    """
    if src.shape != dst.shape or src.dim() < 2 or src.shape[-1] != 3:
        raise ValueError(f"src and dst must both have shape (..., N, 3), got {tuple(src.shape)} "
                         f"and {tuple(dst.shape)}")
    if weights is None:
        weights = torch.ones(src.shape[:-1], dtype=src.dtype, device=src.device)
    elif weights.shape != src.shape[:-1]:
        raise ValueError(f"weights must have shape {tuple(src.shape[:-1])}, got {tuple(weights.shape)}")
    w = weights[..., None]
    wsum = w.sum(dim=-2, keepdim=True).clamp_min(torch.finfo(src.dtype).tiny)
    mu_s = (w * src).sum(dim=-2, keepdim=True) / wsum
    mu_d = (w * dst).sum(dim=-2, keepdim=True) / wsum
    cov = ((dst - mu_d) * w).transpose(-1, -2) @ (src - mu_s)  # (..., 3, 3) = sum w d s^T
    U, _, Vh = torch.linalg.svd(cov)
    sign = torch.sign(torch.linalg.det(U @ Vh))  # +-1: U and Vh are orthogonal
    D = torch.ones(cov.shape[:-1], dtype=src.dtype, device=src.device)
    D[..., 2] = sign
    R = (U * D[..., None, :]) @ Vh
    t = mu_d[..., 0, :] - (R @ mu_s[..., 0, :, None])[..., 0]
    return torch.cat([t, rotmat_to_quat(R)], dim=-1)


def transform_points(pose: Tensor, points: Tensor) -> Tensor:
    """Apply poses ``(..., 7)`` to point sets ``(..., N, 3)`` through rotation matrices (fast for many points).

    Example:
        >>> transform_points(torch.tensor([1., 0, 0, 0, 0, 0, 1]), torch.zeros(4, 3))[:, 0]
        tensor([1., 1., 1., 1.])
    """
    if pose.shape[-1] != 7 or points.shape[-1] != 3:
        raise ValueError(f"pose must be (..., 7) and points (..., N, 3), got {tuple(pose.shape)} "
                         f"and {tuple(points.shape)}")
    R = quat_to_rotmat(pose[..., 3:])
    return points @ R.transpose(-1, -2) + pose[..., None, :3]


def project(points: Tensor, K: Tensor) -> Tensor:
    """Pinhole projection of camera-frame points ``(..., 3)`` to pixels ``(..., 2)`` (z clamped > 0).

    Example:
        >>> project(torch.tensor([[0., 0., 2.]]), torch.tensor([[100., 0, 5], [0, 100., 6], [0, 0, 1]]))
        tensor([[5., 6.]])
    """
    z = points[..., 2:3].clamp_min(1e-6)
    uv = points[..., :2] / z
    return torch.stack([uv[..., 0] * K[0, 0] + K[0, 2], uv[..., 1] * K[1, 1] + K[1, 2]], dim=-1)


def rigid_jacobian(points: Tensor) -> Tensor:
    """Jacobian of ``exp(xi) p`` at ``xi = 0`` for the ``[rho, phi]`` tangent: ``[I, -[p]x]``.

    Args:
        points: ``(N, 3)``.

    Returns:
        ``(N, 3, 6)``.

    Example:
        >>> rigid_jacobian(torch.zeros(2, 3)).shape
        torch.Size([2, 3, 6])
    """
    check_shape(points, (None, 3), "points")
    eye = torch.eye(3, dtype=points.dtype, device=points.device).expand(points.shape[0], 3, 3)
    return torch.cat([eye, -so3_hat(points)], dim=-1)
