"""Depth-to-colour registration of an unregistered RGB-D camera: a z-buffered forward warp.

Every valid depth pixel is moved into the colour camera and splatted to the 2x2 colour pixels around its
projection (no holes from the slight magnification); the nearest wins (docs/api.md, "An unregistered camera").

Example:
    >>> K = torch.tensor([[525., 0., 319.5], [0., 525., 239.5], [0., 0., 1.]], dtype=torch.float64)
    >>> depth = torch.full((480, 640), 2.0)
    >>> out = register_depth_to_color(depth, K, K, torch.tensor([0., 0., 0., 0., 0., 0., 1.]), (480, 640))
    >>> out.shape, float(out[240, 320])
    (torch.Size([480, 640]), 2.0)
"""
from __future__ import annotations

import cv2
import numpy as np
import torch

from slam.lie import quat_to_rotmat, se3_compose, se3_inv
from slam.odometry.geometry import check_shape

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
    check_shape(K_depth, (3, 3), "K_depth")
    check_shape(K_rgb, (3, 3), "K_rgb")
    check_shape(T_rgb_depth, (7,), "T_rgb_depth")
    h, w = int(rgb_size[0]), int(rgb_size[1])
    dtype = depth.dtype if depth.is_floating_point() else torch.float32
    if h <= 0 or w <= 0:
        return torch.zeros(max(h, 0), max(w, 0), dtype=dtype, device=depth.device)
    Kd, Kc = K_depth.to(device=depth.device, dtype=dtype), K_rgb.to(device=depth.device, dtype=dtype)
    T = T_rgb_depth.to(device=depth.device, dtype=dtype)
    R = quat_to_rotmat(T[3:])
    if depth.device.type == "cpu" and dtype in (torch.float32, torch.float64):
        return torch.from_numpy(_warp_numpy(depth.to(dtype).numpy(), Kd.numpy(), Kc.numpy(), R.numpy(),
                                            T[:3].numpy(), h, w, min_depth))
    return _warp_torch(torch.nan_to_num(depth.to(dtype), nan=0.0), Kd, Kc, R, T[:3], h, w, min_depth)


# Both warps are bitwise equal to the four-way scatter of tests/slam/odometry/test_depth_registration.py: the
# z-buffer is a minimum over a grid of splat origins (top-left pixels in [-1, w) x [-1, h)), then a 2x2 minimum.


def _ray_times_depth(row, u, v, d, t):
    """``(row[0] u + row[1] v + row[2]) d + t`` with zero terms and unit factors left out (numpy or torch)."""
    ray = None
    for c, x in ((row[0], u), (row[1], v)):
        if c != 0:
            term = x if c == 1 else c * x
            ray = term if ray is None else ray + term
    if ray is None:
        ray = row[2]
    elif row[2] != 0:
        ray = ray + row[2]
    q = d if (not hasattr(ray, "shape") or ray.shape == ()) and ray == 1 else ray * d
    return q + t if t != 0 else q


def _warp_numpy(d, Kd, Kc, R, t, h: int, w: int, min_depth: float):
    """The z-buffered warp on the CPU (numpy; ``d`` is not modified). Returns ``(h, w)`` of ``d.dtype``."""
    dt = d.dtype.type
    if not np.isfinite(d).all():
        d = np.nan_to_num(d, nan=0.0)  # +-inf become the largest finite values, as torch.nan_to_num does
    H, W = d.shape
    u = ((np.arange(W, dtype=d.dtype) - Kd[0, 2]) / Kd[0, 0])[None, :]
    v = ((np.arange(H, dtype=d.dtype) - Kd[1, 2]) / Kd[1, 1])[:, None]
    # overflow (from a depth of +inf) and 1 / 0 where not ok are masked out below, as in the torch warp
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        qx = _ray_times_depth(R[0], u, v, d, t[0])
        qy = _ray_times_depth(R[1], u, v, d, t[1])
        zc = _ray_times_depth(R[2], u, v, d, t[2])
        md = dt(min_depth)
        ok = d > md
        if zc is not d:
            ok &= zc > md
        inv_z = dt(1.0) / zc  # only read where ok
        x0 = np.floor(qx * inv_z * Kc[0, 0] + Kc[0, 2])
        y0 = np.floor(qy * inv_z * Kc[1, 1] + Kc[1, 2])
    ok &= (x0 >= -1) & (x0 < w) & (y0 >= -1) & (y0 < h)
    sel = np.flatnonzero(ok)
    big = np.finfo(d.dtype).max
    grid = np.full((h + 1) * (w + 1), big, dtype=d.dtype)
    origin = (y0.ravel()[sel].astype(np.intp) + 1) * (w + 1) + x0.ravel()[sel].astype(np.intp) + 1
    np.minimum.at(grid, origin, zc.ravel()[sel])  # zc is (H, W): the ray times the (H, W) depth
    # out[y, x] = min(grid[y:y + 2, x:x + 2]) (grid row/column 0 is origin -1); the border row/column h/w is cut
    z = cv2.erode(grid.reshape(h + 1, w + 1), _ONES_2X2, anchor=(0, 0), borderType=cv2.BORDER_REPLICATE)[:h, :w]
    z = np.ascontiguousarray(z)
    z[z == big] = 0
    return z


_ONES_2X2 = np.ones((2, 2), np.uint8)


def _warp_torch(d: Tensor, Kd: Tensor, Kc: Tensor, R: Tensor, t: Tensor, h: int, w: int,
                min_depth: float) -> Tensor:
    """The same warp in torch (any device; ``d`` already without NaN)."""
    H, W = d.shape
    dev, dtype = d.device, d.dtype
    u = ((torch.arange(W, device=dev, dtype=dtype) - Kd[0, 2]) / Kd[0, 0])[None, :]
    v = ((torch.arange(H, device=dev, dtype=dtype) - Kd[1, 2]) / Kd[1, 1])[:, None]
    qx = (R[0, 0] * u + R[0, 1] * v + R[0, 2]) * d + t[0]
    qy = (R[1, 0] * u + R[1, 1] * v + R[1, 2]) * d + t[1]
    zc = (R[2, 0] * u + R[2, 1] * v + R[2, 2]) * d + t[2]
    ok = (d > min_depth) & (zc > min_depth)
    inv_z = 1.0 / torch.where(ok, zc, torch.ones_like(zc))
    x0 = torch.floor(qx * inv_z * Kc[0, 0] + Kc[0, 2])
    y0 = torch.floor(qy * inv_z * Kc[1, 1] + Kc[1, 2])
    ok = ok & (x0 >= -1) & (x0 < w) & (y0 >= -1) & (y0 < h)
    dummy = (h + 1) * (w + 1)  # one slot past the grid for the points that land nowhere
    origin = torch.where(ok, (y0 + 1) * (w + 1) + (x0 + 1), dummy).reshape(-1).long()
    big = torch.finfo(dtype).max
    grid = torch.full((dummy + 1,), big, dtype=dtype, device=dev)
    grid.scatter_reduce_(0, origin, zc.reshape(-1), reduce="amin")
    g = grid[:dummy].view(h + 1, w + 1)
    z = torch.minimum(torch.minimum(g[:-1, :-1], g[:-1, 1:]), torch.minimum(g[1:, :-1], g[1:, 1:]))
    return torch.where(z < big, z, torch.zeros_like(z))


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
    """Poses of the depth camera from the tracked colour camera's, the world being the first depth camera's:
    ``P_depth = T_rgb_depth^-1 * P_rgb * T_rgb_depth`` (an identity stays an identity).

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
    check_shape(T_rgb_depth, (7,), "T_rgb_depth")
    T = T_rgb_depth.to(rgb_poses)
    return se3_compose(se3_compose(se3_inv(T), rgb_poses), T)
