"""Depth-to-colour registration of an unregistered RGB-D camera (z-buffered forward warp) in torch.

A structured-light sensor such as the Kinect v1 has separate depth (IR) and colour cameras a few
centimetres apart, with different intrinsics. Reading the depth image at a colour keypoint's pixel, even
after rescaling for the focal lengths, reads a different surface point: the parallax is
``f * baseline / z`` pixels (about 10 px at 1.5 m for a 2.5 cm baseline), which moves every keypoint's
depth along slanted surfaces and puts keypoints near silhouettes on the wrong surface. Warping the depth
map into the colour camera, as the OpenNI driver does for registered streams (and as TUM RGB-D ships
its depth), gives each colour pixel its own depth.

Every valid depth pixel is back-projected with the depth intrinsics, moved into the colour camera by
``T_rgb_depth`` and projected with the colour intrinsics; where several land on one colour pixel the
nearest wins (z-buffer). Each point is splatted to the 2x2 colour pixels around its projection so the
slight magnification between the two cameras leaves no holes.

Example:
    >>> K = torch.tensor([[525., 0., 319.5], [0., 525., 239.5], [0., 0., 1.]], dtype=torch.float64)
    >>> depth = torch.full((480, 640), 2.0)
    >>> out = register_depth_to_color(depth, K, K, torch.tensor([0., 0., 0., 0., 0., 0., 1.]), (480, 640))
    >>> out.shape, float(out[240, 320])
    (torch.Size([480, 640]), 2.0)
"""
from __future__ import annotations

import torch

from slam.lie import quat_to_rotmat, se3_compose, se3_inv

Tensor = torch.Tensor

__all__ = ["depth_camera_poses", "register_depth_to_color", "rig_pose"]


def register_depth_to_color(depth: Tensor, K_depth: Tensor, K_rgb: Tensor, T_rgb_depth: Tensor,
                            rgb_size: tuple[int, int], min_depth: float = 0.0) -> Tensor:
    """Depth of every colour pixel, from a depth map taken by another camera.

    Args:
        depth: ``(H, W)`` metres in the depth camera, 0 (or NaN) where invalid.
        K_depth: ``(3, 3)`` depth-camera intrinsics.
        K_rgb: ``(3, 3)`` colour-camera intrinsics.
        T_rgb_depth: ``(7,)`` pose of the depth camera in the colour camera ``[t, q_xyzw]``
            (``p_rgb = R p_depth + t``).
        rgb_size: ``(h, w)`` of the colour image.
        min_depth: depths at or below this are invalid.

    Returns:
        ``(h, w)`` depth along the colour camera's optical axis (metres, the input's float dtype), 0 where
        no depth pixel lands.

    Raises:
        ValueError: for shapes other than the above.
    """
    if depth.dim() != 2:
        raise ValueError(f"depth must have shape (H, W), got {tuple(depth.shape)}")
    for name, K in (("K_depth", K_depth), ("K_rgb", K_rgb)):
        if tuple(K.shape) != (3, 3):
            raise ValueError(f"{name} must have shape (3, 3), got {tuple(K.shape)}")
    if tuple(T_rgb_depth.shape) != (7,):
        raise ValueError(f"T_rgb_depth must have shape (7,), got {tuple(T_rgb_depth.shape)}")
    h, w = int(rgb_size[0]), int(rgb_size[1])
    dtype = depth.dtype if depth.is_floating_point() else torch.float32
    dev = depth.device
    d = torch.nan_to_num(depth.to(dtype), nan=0.0)
    H, W = d.shape
    # Vectorised over the pixel grid (no nonzero / masking: invalid or off-image pixels go to a dummy slot
    # past the end). p_rgb = z * (R ray) + t is affine in z; R ray is built by broadcasting (H, 1) x (1, W).
    Kd = K_depth.to(device=dev, dtype=dtype)
    Kc = K_rgb.to(device=dev, dtype=dtype)
    T = T_rgb_depth.to(device=dev, dtype=dtype)
    R = quat_to_rotmat(T[3:])
    u = ((torch.arange(W, device=dev, dtype=dtype) - Kd[0, 2]) / Kd[0, 0])[None, :]
    v = ((torch.arange(H, device=dev, dtype=dtype) - Kd[1, 2]) / Kd[1, 1])[:, None]
    qx = (R[0, 0] * u + R[0, 1] * v + R[0, 2]) * d + T[0]
    qy = (R[1, 0] * u + R[1, 1] * v + R[1, 2]) * d + T[1]
    zc = (R[2, 0] * u + R[2, 1] * v + R[2, 2]) * d + T[2]
    ok = (d > min_depth) & (zc > min_depth)
    inv_z = 1.0 / torch.where(ok, zc, torch.ones_like(zc))
    x0 = torch.floor(qx * inv_z * Kc[0, 0] + Kc[0, 2])
    y0 = torch.floor(qy * inv_z * Kc[1, 1] + Kc[1, 2])
    # a point lands between four colour pixels: splat it on all four (the depth camera's finer sampling
    # would otherwise leave holes); -1 <= x0 < w keeps the ones whose right/lower neighbour is inside
    ok = (ok & (x0 >= -1) & (x0 < w) & (y0 >= -1) & (y0 < h)).reshape(-1)
    x0 = torch.where(ok, x0.reshape(-1), 0).long()  # 0 where not ok: no cast of inf/NaN
    y0 = torch.where(ok, y0.reshape(-1), 0).long()
    dummy = h * w
    base = y0 * w + x0
    left, right = ok & (x0 >= 0), ok & (x0 + 1 < w)
    top, bottom = y0 >= 0, y0 + 1 < h
    idx = torch.cat([
        torch.where(left & top, base, dummy),
        torch.where(right & top, base + 1, dummy),
        torch.where(left & bottom, base + w, dummy),
        torch.where(right & bottom, base + w + 1, dummy),
    ])
    big = torch.finfo(dtype).max
    zbuf = torch.full((h * w + 1,), big, dtype=dtype, device=dev)
    zbuf.scatter_reduce_(0, idx, zc.reshape(-1).repeat(4), reduce="amin")
    zbuf = zbuf[:dummy]
    return torch.where(zbuf < big, zbuf, torch.zeros_like(zbuf)).reshape(h, w)


def rig_pose(rgb_from_depth_translation, dtype=torch.float64, device=None) -> Tensor:
    """``(7,)`` pose ``T_rgb_depth`` of a rig whose two cameras have parallel axes.

    Example:
        >>> rig_pose((-0.025, 0.0, 0.0)).tolist()
        [-0.025, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    """
    t = [float(x) for x in rgb_from_depth_translation]
    if len(t) != 3:
        raise ValueError(f"rgb_from_depth_translation must have 3 entries, got {len(t)}")
    return torch.tensor([*t, 0.0, 0.0, 0.0, 1.0], dtype=dtype, device=device)


def depth_camera_poses(rgb_poses: Tensor, T_rgb_depth: Tensor) -> Tensor:
    """Poses of the depth camera from the tracked colour camera's, the world being the first depth camera's.

    ``P_depth = T_rgb_depth^-1 * P_rgb * T_rgb_depth``: right, the depth camera rides on the colour
    camera; left, the world frame (the first colour camera's, where tracking starts) moves to the first
    depth camera's, so an identity stays an identity.

    Args:
        rgb_poses: ``(..., 7)`` world-from-colour-camera poses.
        T_rgb_depth: ``(7,)`` pose of the depth camera in the colour camera.

    Returns:
        ``(..., 7)`` world-from-depth-camera poses.

    Example:
        >>> T = torch.tensor([-0.025, 0., 0., 0., 0., 0., 1.])
        >>> depth_camera_poses(torch.tensor([[0., 0., 0., 0., 0., 0., 1.]]), T)
        tensor([[0., 0., 0., 0., 0., 0., 1.]])
    """
    if tuple(T_rgb_depth.shape) != (7,):
        raise ValueError(f"T_rgb_depth must have shape (7,), got {tuple(T_rgb_depth.shape)}")
    T = T_rgb_depth.to(rgb_poses)
    return se3_compose(se3_compose(se3_inv(T), rgb_poses), T)
