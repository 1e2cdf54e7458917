"""A ray caster in torch for :class:`~slam.synthetic.scene.Scene` (slab method per box, trilinear mip-mapped
textures, Lambertian point lights without shadows: a surface point has one colour in every view), plus Kinect-like
sensor noise and motion blur. Pinhole ``K (3, 3)``, pixel ``(u, v)`` = (column, row), camera x right, y down,
z forward; poses ``(..., 7) = [t, q_xyzw]`` camera-to-world; depth is the z-depth, 0 where nothing is hit.

Example:
    >>> from slam.synthetic.scene import RoomConfig, build_room_scene
    >>> scene = build_room_scene(RoomConfig(texel_density=32.0, object_texel_density=32.0))
    >>> K = torch.tensor([[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]], dtype=torch.float64)
    >>> pose = torch.tensor([[3.5, 3.0, 1.4, -0.5, 0.5, -0.5, 0.5]], dtype=torch.float64)
    >>> out = render_frames(scene, K, pose, 24, 32)
    >>> out.rgb.shape, out.rgb.dtype, out.depth.shape, out.depth.dtype
    (torch.Size([1, 24, 32, 3]), torch.uint8, torch.Size([1, 24, 32]), torch.float32)
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F

from slam.lie import quat_conj, quat_mul, quat_normalize, quat_to_rotmat, so3_exp, so3_log
from slam.synthetic.scene import Scene

Tensor = torch.Tensor

__all__ = [
    "DepthNoiseConfig",
    "ImageNoiseConfig",
    "RenderOutput",
    "apply_depth_noise",
    "apply_image_noise",
    "apply_motion_blur",
    "frame_generator",
    "pixel_rays",
    "render_frames",
]

_NEAR = 1e-4  # metres: hits closer than this along the ray are ignored (the ray's own origin)


class RenderOutput(NamedTuple):
    """What :func:`render_frames` returns for N frames of H x W pixels.

    Attributes:
        rgb: ``(N, H, W, 3)`` uint8.
        depth: ``(N, H, W)`` float32 z-depth in metres, 0 where no surface is hit.
        cos_incidence: ``(N, H, W)`` float32 ``|cos|`` of the angle between ray and surface normal.
        hit: ``(N, H, W)`` int64 ``box * 6 + face`` of the visible surface, -1 where nothing is hit.
    """

    rgb: Tensor
    depth: Tensor
    cos_incidence: Tensor
    hit: Tensor


@dataclass(frozen=True)
class DepthNoiseConfig:
    """Kinect-v1-like depth corruption (all seeded per frame).

    Attributes:
        sigma_base: axial noise std (m) at ``sigma_ref`` (Nguyen et al. 2012).
        sigma_quad: growth of the std with ``(z - sigma_ref)^2`` (m per m^2).
        sigma_ref: depth (m) where the std is smallest.
        focal_baseline: IR focal length (px) x projector baseline (m), for the disparity quantisation.
        disparity_step: disparity resolution in pixels (Kinect v1: 1/8); 0 disables the quantisation.
        min_depth: nearer surfaces read as invalid (m).
        max_depth: farther surfaces read as invalid (m).
        dropout: fraction of ``dropout_block``-pixel square blobs dropped at random (holes).
        dropout_block: side of a dropped blob in pixels.
        edge_jump: a pixel whose 3x3 neighbourhood spans more than ``edge_jump * z`` in depth is
            invalid (the sensor's missing readings at occluding edges).
        min_cos_incidence: surfaces seen more grazingly than this (|cos| below) read as invalid.
        disparity_distortion: a fixed-pattern disparity error (pixels), growing with the squared distance from
            the image centre to this value at the corners (Herrera et al. 2012). 0: none.
        noise_correlation_px: Gaussian sigma (pixels) of the spatial correlation of the axial noise (the std
            stays ``sigma(z)``). 0: independent pixels.
    """

    sigma_base: float = 0.0012
    sigma_quad: float = 0.0019
    sigma_ref: float = 0.4
    focal_baseline: float = 43.5
    disparity_step: float = 0.125
    min_depth: float = 0.4
    max_depth: float = 8.0
    dropout: float = 0.005
    dropout_block: int = 4
    edge_jump: float = 0.05
    min_cos_incidence: float = 0.1
    disparity_distortion: float = 0.0
    noise_correlation_px: float = 0.0


@dataclass(frozen=True)
class ImageNoiseConfig:
    """Photometric corruption of the colour images (seeded per frame) and motion blur.

    Attributes:
        exposure_sigma: std of the per-frame multiplicative gain (auto-exposure flicker).
        offset_sigma: std of the per-frame additive offset, grey levels.
        pixel_sigma: std of the per-pixel, per-channel Gaussian noise, grey levels.
        exposure_time: the colour camera's exposure in seconds (:func:`apply_motion_blur`). 0: sharp images.
        blur_samples: instants averaged over the exposure.
    """

    exposure_sigma: float = 0.03
    offset_sigma: float = 2.0
    pixel_sigma: float = 1.5
    exposure_time: float = 0.0
    blur_samples: int = 9

    def __post_init__(self) -> None:
        if not (self.exposure_time >= 0 and math.isfinite(self.exposure_time)):
            raise ValueError(f"ImageNoiseConfig.exposure_time must be finite and >= 0, got {self.exposure_time!r}")
        if int(self.blur_samples) < 2:
            raise ValueError(f"ImageNoiseConfig.blur_samples must be >= 2, got {self.blur_samples!r}")


def pixel_rays(K: Tensor, height: int, width: int) -> Tensor:
    """Camera-frame ray directions ``(H * W, 3)`` through every pixel centre, scaled to z = 1.

    Args:
        K: ``(3, 3)`` intrinsics.
    """
    if K.shape != (3, 3):
        raise ValueError(f"K must have shape (3, 3), got {tuple(K.shape)}")
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64, device=K.device),
                          torch.arange(width, dtype=torch.float64, device=K.device), indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], -1).reshape(-1, 3)
    rays = torch.linalg.solve(K.to(torch.float64), pix.T).T
    return rays / rays[:, 2:3]


def _slab(o_l: Tensor, d_l: Tensor, half: Tensor, inside: bool):
    """Ray parameter ``(M,)`` (inf on a miss) and face ``(M,)`` of one box for rays ``o_l (3, 1) or (3, M)``,
    ``d_l (3, M)`` in its local frame, ``half (3, 1)``: the entry face, or the exit face seen from inside (the
    room). A NaN (origin on a face's plane) misses."""
    inv = 1.0 / d_l
    t_lo = (-half - o_l) * inv
    t_hi = (half - o_l) * inv
    positive = d_l > 0
    if inside:
        t, axis = torch.maximum(t_lo, t_hi).min(0)
        face = 2 * axis + torch.gather(positive, 0, axis[None])[0].long()
        return torch.where(t > _NEAR, t, torch.full_like(t, float("inf"))), face
    t_near, axis = torch.minimum(t_lo, t_hi).max(0)
    t_far = torch.maximum(t_lo, t_hi).min(0).values
    face = 2 * axis + (~torch.gather(positive, 0, axis[None])[0]).long()
    return torch.where((t_near <= t_far) & (t_near > _NEAR), t_near, torch.full_like(t_near, float("inf"))), face


def _sample_texture(scene: Scene, tex: Tensor, u: Tensor, v: Tensor, level: Tensor) -> Tensor:
    """Trilinear lookup ``(M, 3)`` float32 RGB in [0, 255] of texture ids ``tex (M,)`` at ``u, v (M,)`` in [0, 1]
    (columns, rows) and continuous mip ``level (M,)``."""
    num_levels = scene.tex_offset.shape[1]
    level = level.float().clamp(0.0, num_levels - 1)
    l0 = level.floor()
    wl = level - l0
    row0 = tex * num_levels + l0.long()
    out = torch.zeros(tex.shape[0], 3, dtype=torch.float32, device=tex.device)
    offsets, sizes = scene.tex_offset.reshape(-1), scene.tex_size.reshape(-1, 2)
    row1 = torch.where(l0 < num_levels - 1, row0 + 1, row0)  # the next level, clamped at the coarsest
    for row, w_level in ((row0, 1.0 - wl), (row1, wl)):
        off = offsets.index_select(0, row)
        Wd, Hd = sizes.index_select(0, row).unbind(1)
        x = u * Wd - 0.5
        y = v * Hd - 0.5
        x0f, y0f = x.floor(), y.floor()
        fx, fy = x - x0f, y - y0f
        x0, y0 = x0f.long(), y0f.long()
        xa = torch.minimum(x0.clamp_min(0), Wd - 1)
        xb = torch.minimum((x0 + 1).clamp_min(0), Wd - 1)
        ya = torch.minimum(y0.clamp_min(0), Hd - 1) * Wd + off
        yb = torch.minimum((y0 + 1).clamp_min(0), Hd - 1) * Wd + off
        gx, gy = 1.0 - fx, 1.0 - fy
        for idx, w in ((ya + xa, gx * gy), (ya + xb, fx * gy), (yb + xa, gx * fy), (yb + xb, fx * fy)):
            out.addcmul_(scene.tex_buffer.index_select(0, idx).float(), (w * w_level)[:, None])
    return out


def _face_table(scene: Scene) -> Tensor:
    """Per face (column ``box * 6 + face``) in world coordinates: texture origin (3), u axis / extent (3),
    v axis / extent (3), visible-side normal (3), texel density (1) -> ``(13, B * 6)`` float32."""
    R = scene.rotations[:, None]  # (B, 1, 3, 3)
    origin = (R @ scene.face_origin[..., None])[..., 0] + scene.centers[:, None]
    u = (R @ scene.face_u[..., None])[..., 0] / scene.face_extent[..., 0:1]
    v = (R @ scene.face_v[..., None])[..., 0] / scene.face_extent[..., 1:2]
    n = (R @ scene.face_normal[..., None])[..., 0]
    table = torch.cat([origin, u, v, n, scene.face_density[..., None]], -1)
    return table.reshape(-1, 13).float().T.contiguous()


_BOX_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
# the 12 edges of a box as pairs of indices into _BOX_SIGNS (corners differing in one sign)
_BOX_EDGES = np.array([(a, b) for a in range(8) for b in range(a + 1, 8)
                       if int(np.abs(_BOX_SIGNS[a] - _BOX_SIGNS[b]).sum()) == 2], np.int64)


def _np64(x: Tensor) -> np.ndarray:
    return x.detach().cpu().double().numpy()


def _box_corners(scene: Scene) -> np.ndarray:
    """World corners ``(B, 8, 3)`` float64 of every box."""
    h = _np64(scene.half_sizes)
    return _np64(scene.centers)[:, None, :] + np.einsum("bkj,bij->bki", _BOX_SIGNS[None] * h[:, None, :],
                                                         _np64(scene.rotations))


def _screen_rects(corners: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray, height: int,
                  width: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel rectangles ``(B, 4)`` int64 ``(u0, u1, v0, v1)`` (end-exclusive) that contain each box's image,
    and a ``(B,)`` bool mask of the boxes that can be seen at all: the hull of the projections of its corners
    in front of the plane ``z = _NEAR`` and of the points where its edges cross that plane."""
    cam = (corners - t) @ R  # (B, 8, 3), world -> camera: R^T (X - t)
    z = cam[..., 2]
    p0, p1 = cam[:, _BOX_EDGES[:, 0]], cam[:, _BOX_EDGES[:, 1]]  # (B, 12, 3)
    z0, z1 = p0[..., 2], p1[..., 2]
    crossing = (z0 - _NEAR) * (z1 - _NEAR) < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        alpha = np.where(crossing, (_NEAR - z0) / (z1 - z0), 0.0)
    cut = p0 + alpha[..., None] * (p1 - p0)
    pts = np.concatenate([cam, cut], 1)  # (B, 20, 3)
    valid = np.concatenate([z > _NEAR, crossing], 1)
    zz = np.where(valid, np.maximum(pts[..., 2], _NEAR), 1.0)
    uv = np.stack([K[0, 0] * pts[..., 0] / zz + K[0, 2], K[1, 1] * pts[..., 1] / zz + K[1, 2]], -1)  # (B, 20, 2)
    lo = np.floor(np.clip(np.where(valid[..., None], uv, 1e18).min(1), -1e9, 1e9)) - 1  # (B, 2): u, v
    hi = np.ceil(np.clip(np.where(valid[..., None], uv, -1e18).max(1), -1e9, 1e9)) + 2
    rects = np.clip(np.stack([lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1]], 1), 0, [width, width, height, height])
    rects = rects.astype(np.int64)
    return rects, valid.any(1) & (rects[:, 0] < rects[:, 1]) & (rects[:, 2] < rects[:, 3])


def _trace_frame(scene: Scene, R: Tensor, t: Tensor, rays_c: Tensor, K: Tensor, height: int, width: int,
                 corners: np.ndarray):
    """Nearest hit (t, box, face) of every pixel ray ``rays_c (3, P)`` of one camera; a box is only tested
    inside its screen rectangle (:func:`_screen_rects` of ``corners``, :func:`_box_corners`)."""
    dirs = R @ rays_c  # (3, P) world directions
    rects, seen = _screen_rects(corners, _np64(R), _np64(t), _np64(K), height, width)
    t_img = torch.full((height, width), float("inf"), dtype=dirs.dtype, device=dirs.device)
    box_img = torch.zeros(height, width, dtype=torch.int64, device=dirs.device)
    face_img = torch.zeros_like(box_img)
    dirs_img = dirs.view(3, height, width)
    for b in range(scene.num_boxes):
        RbT = scene.rotations[b].to(dirs.dtype).T
        o_l = (RbT @ (t - scene.centers[b].to(dirs.dtype)))[:, None]
        half = scene.half_sizes[b].to(dirs.dtype)[:, None]
        inside = bool(scene.inside[b])
        if not (inside or seen[b]):
            continue
        u0, u1, v0, v1 = (0, width, 0, height) if inside else rects[b].tolist()
        sub = dirs_img[:, v0:v1, u0:u1].reshape(3, -1)
        tb, fb = (x.view(v1 - v0, u1 - u0) for x in _slab(o_l, RbT @ sub, half, inside))
        cur = t_img[v0:v1, u0:u1]
        better = tb < cur
        t_img[v0:v1, u0:u1] = torch.where(better, tb, cur)
        box_img[v0:v1, u0:u1] = torch.where(better, torch.full_like(fb, b), box_img[v0:v1, u0:u1])
        face_img[v0:v1, u0:u1] = torch.where(better, fb, face_img[v0:v1, u0:u1])
    return dirs, t_img.view(-1), box_img.view(-1), face_img.view(-1)


def _norm0(x: Tensor) -> Tensor:
    """Euclidean norm over dim 0 of ``(3, P)`` (torch's ``norm(dim=0)`` is ~50x slower on CPU here)."""
    return (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt()


def _shade(scene: Scene, table: Tensor, origin: Tensor, dirs: Tensor, t: Tensor, box: Tensor, face: Tensor,
           R: Tensor, fx: float, fy: float):
    """Colour ``(P, 3)`` float, ``|cos|`` ``(P,)`` and hit id ``(P,)`` of traced rays ``dirs (3, P)``."""
    hit = torch.isfinite(t)
    t = torch.where(hit, t, torch.zeros_like(t))
    bf = box * 6 + face
    rows = table.index_select(1, bf)  # (13, P)
    p_w = origin[:, None] + t * dirs  # (3, P)
    rel = p_w - rows[0:3]
    u = (rel * rows[3:6]).sum(0).clamp_(0.0, 1.0)
    v = (rel * rows[6:9]).sum(0).clamp_(0.0, 1.0)
    n_w = rows[9:12]
    # Exact footprint of a one-pixel step on the surface's plane: dp/du = t/fx (a - d (n.a) / (n.d)),
    # with a, b the camera's x and y axes in the world; its longer side picks the mip level.
    nd = (n_w * dirs).sum(0)
    nd = torch.where(nd.abs() < 1e-9, torch.full_like(nd, -1e-9), nd)
    a, b = R[:, 0], R[:, 1]
    step_x = _norm0(dirs * ((a @ n_w) / nd) - a[:, None]) * (t / fx)
    step_y = _norm0(dirs * ((b @ n_w) / nd) - b[:, None]) * (t / fy)
    level = torch.log2((torch.maximum(step_x, step_y) * rows[12]).clamp_min(1e-6))
    albedo = _sample_texture(scene, scene.face_tex.reshape(-1).index_select(0, bf), u, v, level)
    # Lambertian shading from point lights (no shadows) with a soft distance fall-off.
    diffuse = torch.zeros_like(t)
    for light in scene.lights:
        to_light = light[:, None] - p_w
        dist = _norm0(to_light).clamp_min(1e-6)
        diffuse += ((to_light * n_w).sum(0) / dist).clamp_min(0.0) / (1.0 + (dist / 3.0) ** 2)
    shade = scene.ambient + (1.0 - scene.ambient) * 1.6 * diffuse.clamp(max=1.0)
    rgb = albedo * torch.where(hit, shade, torch.zeros_like(shade))[:, None]
    cos_inc = torch.where(hit, nd.abs() / _norm0(dirs), torch.zeros_like(nd))
    hit_id = torch.where(hit, bf, torch.full_like(bf, -1))
    return t, rgb.clamp(0.0, 255.0), cos_inc, hit_id


def render_frames(scene: Scene, K: Tensor, poses: Tensor, height: int, width: int) -> RenderOutput:
    """Render N views of the scene in float32 on the scene's device (depth exact to ~1e-6 m at room scale).

    Args:
        scene: the scene.
        K: ``(3, 3)`` pinhole intrinsics.
        poses: ``(N, 7)`` or ``(7,)`` camera-to-world ``[t, q_xyzw]``.
        height, width: image rows H and columns W.

    Returns:
        :class:`RenderOutput` with ``(N, H, W, ...)`` tensors on the scene's device.
    """
    if poses.ndim == 1:
        poses = poses[None]
    if poses.ndim != 2 or poses.shape[-1] != 7:
        raise ValueError(f"poses must have shape (N, 7) or (7,), got {tuple(poses.shape)}")
    if height <= 0 or width <= 0:
        raise ValueError(f"height and width must be positive, got {height} x {width}")
    device = scene.device
    N = poses.shape[0]
    Kf = K.to(device=device, dtype=torch.float32)
    rays_c = pixel_rays(K.to(device), height, width).float().T.contiguous()
    poses = poses.to(device=device, dtype=torch.float64)
    Rs = quat_to_rotmat(quat_normalize(poses[:, 3:])).float()
    ts = poses[:, :3].float()
    fx, fy = float(K[0, 0]), float(K[1, 1])
    rgb = torch.zeros(N, height * width, 3, dtype=torch.uint8, device=device)
    depth = torch.zeros(N, height * width, dtype=torch.float32, device=device)
    cos_inc = torch.zeros_like(depth)
    hit = torch.zeros(N, height * width, dtype=torch.int64, device=device)
    table = _face_table(scene)
    corners = _box_corners(scene)
    for i in range(N):
        dirs, t, box, face = _trace_frame(scene, Rs[i], ts[i], rays_c, Kf, height, width, corners)
        d, c, ci, h = _shade(scene, table, ts[i], dirs, t, box, face, Rs[i], fx, fy)
        depth[i], rgb[i], cos_inc[i], hit[i] = d, c.round().to(torch.uint8), ci, h
    return RenderOutput(rgb=rgb.reshape(N, height, width, 3), depth=depth.reshape(N, height, width),
                        cos_incidence=cos_inc.reshape(N, height, width), hit=hit.reshape(N, height, width))


def frame_generator(seed: int, index: int, stream: int) -> torch.Generator:
    """A CPU generator for one frame and one noise stream: independent of batching and frame order."""
    g = torch.Generator(device="cpu")
    g.manual_seed((int(seed) * 1_000_003 + int(index) * 7 + int(stream)) % (2 ** 63 - 1))
    return g


def apply_depth_noise(depth: Tensor, cos_incidence: Tensor, config: DepthNoiseConfig,
                      seeds: Sequence[int]) -> Tensor:
    """Kinect-like noise, quantisation and invalid pixels on z-depth maps.

    Args:
        depth: ``(N, H, W)`` float32 metres, 0 = invalid.
        cos_incidence: ``(N, H, W)`` ``|cos|`` of the incidence angle (from :func:`render_frames`).
        config: the noise model.
        seeds: N integers, one per frame (the noise of a frame depends only on its seed).

    Returns:
        ``(N, H, W)`` float32 noisy depth, 0 = invalid.
    """
    if depth.ndim != 3 or cos_incidence.shape != depth.shape:
        raise ValueError(f"depth and cos_incidence must both be (N, H, W), got {tuple(depth.shape)} and "
                         f"{tuple(cos_incidence.shape)}")
    if len(seeds) != depth.shape[0]:
        raise ValueError(f"need one seed per frame: {depth.shape[0]} frames, {len(seeds)} seeds")
    N, H, W = depth.shape
    out = torch.empty_like(depth)
    b = max(1, int(config.dropout_block))
    hb, wb = -(-H // b), -(-W // b)
    smooth = None
    if config.noise_correlation_px > 0:  # separable Gaussian whose 2-D squares sum to 1: unit variance kept
        r = max(1, math.ceil(3 * config.noise_correlation_px))
        smooth = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float32) / config.noise_correlation_px) ** 2)
        smooth = (smooth / smooth.square().sum().sqrt()).to(depth.device)
    pattern = None
    if config.disparity_distortion != 0:
        v, u = torch.meshgrid(torch.linspace(-1.0, 1.0, H), torch.linspace(-1.0, 1.0, W), indexing="ij")
        pattern = (config.disparity_distortion * 0.5 * (u * u + v * v)).to(depth.device)  # 1 at the corners
    for i in range(N):
        z = depth[i]
        g = frame_generator(seeds[i], 0, 1)
        gauss = torch.randn(H, W, generator=g).to(z.device)
        if smooth is not None:
            x = F.conv2d(F.pad(gauss[None, None], (r, r, 0, 0), mode="reflect"), smooth.view(1, 1, 1, -1))
            gauss = F.conv2d(F.pad(x, (0, 0, r, r), mode="reflect"), smooth.view(1, 1, -1, 1))[0, 0]
        holes = (torch.rand(hb, wb, generator=g) < config.dropout).to(z.device)
        holes = holes.repeat_interleave(b, 0).repeat_interleave(b, 1)[:H, :W]
        valid = z > 0
        # Occluding edges: the 3x3 depth range is large compared with the depth itself.
        zz = torch.where(valid, z, torch.zeros_like(z))[None, None]
        zmax = F.max_pool2d(zz, 3, 1, 1)[0, 0]
        zmin = -F.max_pool2d(torch.where(zz > 0, -zz, torch.full_like(zz, -1e9)), 3, 1, 1)[0, 0]
        edge = (zmax - zmin) > config.edge_jump * z
        sigma = config.sigma_base + config.sigma_quad * (z - config.sigma_ref) ** 2
        zn = z + sigma * gauss
        if pattern is not None or config.disparity_step > 0:
            disp = config.focal_baseline / zn.clamp_min(1e-3)
            if pattern is not None:  # the fixed-pattern disparity error of the sensor's calibration
                disp = disp + pattern
            if config.disparity_step > 0:  # the sensor measures disparity in 1/8 px steps
                disp = torch.round(disp / config.disparity_step) * config.disparity_step
            zn = config.focal_baseline / disp.clamp_min(1e-6)
        keep = (valid & ~edge & ~holes & (cos_incidence[i] >= config.min_cos_incidence)
                & (zn >= config.min_depth) & (zn <= config.max_depth))
        out[i] = torch.where(keep, zn, torch.zeros_like(zn))
    return out


def apply_image_noise(rgb: Tensor, config: ImageNoiseConfig, seeds: Sequence[int]) -> Tensor:
    """Per-frame exposure gain/offset and per-pixel Gaussian noise on colour images.

    Args:
        rgb: ``(N, H, W, 3)`` uint8.
        config: the noise model.
        seeds: N integers, one per frame.

    Returns:
        ``(N, H, W, 3)`` uint8.
    """
    if rgb.ndim != 4 or rgb.shape[-1] != 3:
        raise ValueError(f"rgb must have shape (N, H, W, 3), got {tuple(rgb.shape)}")
    if len(seeds) != rgb.shape[0]:
        raise ValueError(f"need one seed per frame: {rgb.shape[0]} frames, {len(seeds)} seeds")
    out = torch.empty_like(rgb)
    for i in range(rgb.shape[0]):
        g = frame_generator(seeds[i], 0, 2)
        gain = 1.0 + config.exposure_sigma * float(torch.randn(1, generator=g))
        offset = config.offset_sigma * float(torch.randn(1, generator=g))
        noise = (config.pixel_sigma * torch.randn(rgb.shape[1:], generator=g)).to(rgb.device)
        img = rgb[i].float() * gain + offset + noise
        out[i] = img.round().clamp(0, 255).to(torch.uint8)
    return out


def _toward(poses: Tensor, others: Tensor, f: float) -> Tensor:
    """Poses ``(N, 7)`` moved a fraction ``f`` of the way to ``others (N, 7)`` (translation linearly,
    rotation along the geodesic)."""
    q = quat_normalize(poses[:, 3:])
    dq = so3_log(quat_mul(quat_conj(q), quat_normalize(others[:, 3:])))
    return torch.cat([poses[:, :3] + f * (others[:, :3] - poses[:, :3]), quat_mul(q, so3_exp(f * dq))], -1)


def apply_motion_blur(rgb: Tensor, depth: Tensor, K: Tensor, poses: Tensor, before: Tensor, after: Tensor,
                      fraction: float, samples: int = 9) -> Tensor:
    """Screen-space motion blur of a moving camera in a static scene, from each sharp frame and its exact depth:
    each pixel averages the sharp image over ``samples`` instants of an exposure centred on the frame's pose, at
    the mirror of its surface point's path; pixels without depth keep their colour.

    Args:
        rgb: ``(N, H, W, 3)`` uint8 sharp frames.
        depth: ``(N, H, W)`` float32 z-depth (metres, 0 = none) of the same frames, noise-free.
        K: ``(3, 3)`` intrinsics.
        poses, before, after: ``(N, 7)`` camera-to-world poses of each frame, the previous and the next
            frame (a frame's own pose where it has no neighbour).
        fraction: exposure / frame interval (e.g. 0.02 s at 30 Hz: 0.6), in ``[0, 2]``.
        samples: instants averaged (>= 2).

    Returns:
        ``(N, H, W, 3)`` uint8 blurred frames (``rgb`` itself when ``fraction`` is 0).
    """
    if rgb.ndim != 4 or rgb.shape[-1] != 3 or depth.shape != rgb.shape[:3]:
        raise ValueError(f"expected rgb (N, H, W, 3) and depth (N, H, W), got {tuple(rgb.shape)} and "
                         f"{tuple(depth.shape)}")
    N, H, W = depth.shape
    for name, p in (("poses", poses), ("before", before), ("after", after)):
        if p.shape != (N, 7):
            raise ValueError(f"{name} must have shape ({N}, 7), got {tuple(p.shape)}")
    if not 0.0 <= fraction <= 2.0:
        raise ValueError(f"fraction must be in [0, 2], got {fraction}")
    if fraction == 0.0:
        return rgb
    if samples < 2:
        raise ValueError(f"samples must be >= 2, got {samples}")
    dev = rgb.device
    Kd = K.to(device=dev, dtype=torch.float64)
    rays = pixel_rays(Kd, H, W)  # (H * W, 3), z = 1
    P = poses.to(device=dev, dtype=torch.float64)
    Rs = quat_to_rotmat(quat_normalize(P[:, 3:]))
    out = torch.empty_like(rgb)
    # instants in [-fraction/2, fraction/2] of the frame interval, symmetric about the frame's pose
    offsets = [fraction * (k / (samples - 1) - 0.5) for k in range(samples)]
    for i in range(N):
        z = depth[i].reshape(-1).to(torch.float64)
        world = (rays * z[:, None]) @ Rs[i].T + P[i, :3]  # (H * W, 3)
        img = rgb[i].permute(2, 0, 1)[None].float()  # (1, 3, H, W)
        acc = torch.zeros(3, H * W, dtype=torch.float32, device=dev)
        u0 = rays[:, 0] * Kd[0, 0] + Kd[0, 2]
        v0 = rays[:, 1] * Kd[1, 1] + Kd[1, 2]
        ok = z > 0
        for s in offsets:
            nb = after[i:i + 1] if s > 0 else before[i:i + 1]
            Ps = _toward(P[i:i + 1], nb.to(device=dev, dtype=torch.float64), abs(s))[0]
            cam = (world - Ps[:3]) @ quat_to_rotmat(Ps[3:])  # R^T (X - t)
            zc = cam[:, 2].clamp_min(1e-6)
            u = Kd[0, 0] * cam[:, 0] / zc + Kd[0, 2]
            v = Kd[1, 1] * cam[:, 1] / zc + Kd[1, 2]
            # the colour that reaches pixel p at this instant left the point that is at p - (flow) in the
            # sharp frame: sample there (mirror of the point's own motion)
            us = torch.where(ok, 2 * u0 - u, u0)
            vs = torch.where(ok, 2 * v0 - v, v0)
            grid = torch.stack([2 * us / (W - 1) - 1, 2 * vs / (H - 1) - 1], -1).float().view(1, H, W, 2)
            acc += F.grid_sample(img, grid, mode="bilinear", padding_mode="border",
                                 align_corners=True)[0].reshape(3, -1)
        out[i] = (acc / samples).round().clamp(0, 255).to(torch.uint8).reshape(3, H, W).permute(1, 2, 0)
    return out
