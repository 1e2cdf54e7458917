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

__all__ = ["depth_camera_poses", "register_depth_to_color"]


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
    v, u = torch.nonzero(d > min_depth, as_tuple=True)
    out = torch.zeros(h * w, dtype=dtype, device=dev)
    if v.numel() == 0:
        return out.reshape(h, w)
    z = d[v, u]
    Kd = K_depth.to(device=dev, dtype=torch.float64)
    Kc = K_rgb.to(device=dev, dtype=torch.float64)
    # float64 for the geometry: 640 px * 1e-7 relative error of float32 is harmless, but cheap to avoid
    z64 = z.to(torch.float64)
    p = torch.stack([(u - Kd[0, 2]) / Kd[0, 0] * z64, (v - Kd[1, 2]) / Kd[1, 1] * z64, z64], dim=-1)
    T = T_rgb_depth.to(device=dev, dtype=torch.float64)
    q = p @ quat_to_rotmat(T[3:]).T + T[:3]
    zc = q[:, 2]
    front = zc > min_depth
    q, zc = q[front], zc[front]
    x = Kc[0, 0] * q[:, 0] / zc + Kc[0, 2]
    y = Kc[1, 1] * q[:, 1] / zc + Kc[1, 2]
    x0, y0 = torch.floor(x).long(), torch.floor(y).long()
    big = torch.finfo(dtype).max
    zbuf = torch.full((h * w,), big, dtype=dtype, device=dev)
    zc_t = zc.to(dtype)
    for dx in (0, 1):
        for dy in (0, 1):
            xi, yi = x0 + dx, y0 + dy
            ok = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
            zbuf.scatter_reduce_(0, (yi[ok] * w + xi[ok]), zc_t[ok], reduce="amin")
    return torch.where(zbuf < big, zbuf, out).reshape(h, w)


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
