"""Keypoints with descriptors and 3D points (OpenCV ORB or SIFT, bucketed, back-projected with the depth).

Example:
    >>> rgb = np.zeros((48, 64, 3), np.uint8)
    >>> depth = np.zeros((48, 64), np.float32)
    >>> K = np.array([[50., 0, 32], [0, 50., 24], [0, 0, 1]])
    >>> f = extract_features(rgb, depth, K)
    >>> f.keypoints.shape, f.descriptors.shape, f.points.shape, f.num_valid
    (torch.Size([0, 2]), torch.Size([0, 32]), torch.Size([0, 3]), 0)
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Union

import cv2
import numpy as np
import torch

from slam.odometry.config import FeatureConfig
from slam.odometry.depth_registration import register_depth_to_color, rig_pose
from slam.odometry.geometry import backproject

Tensor = torch.Tensor
ArrayLike = Union[np.ndarray, Tensor]

__all__ = ["FrameFeatures", "bucket_keypoints", "extract_features"]


@dataclass
class FrameFeatures:
    """Keypoints, descriptors and 3D points of one frame (everything registration needs).

    Attributes:
        keypoints: ``(N, 2)`` float32 pixel coordinates ``(x, y)`` in the full-size colour image.
        descriptors: ``(N, D)``: uint8 packed bits for binary descriptors (ORB: ``D = 32``), float32
            unit vectors otherwise (RootSIFT: ``D = 128``).
        points: ``(N, 3)`` float32 metres in the tracked camera's frame (zeros where ``valid`` is False).
        valid: ``(N,)`` bool, the keypoint has a trustworthy depth.
        sigma_px: ``(N,)`` float32 keypoint position std in pixels (grows with the pyramid level).
        K: ``(3, 3)`` float64 intrinsics of the keypoints' image (``FeatureConfig.rgb_intrinsics`` or the frame's).
        image_size: ``(H, W)``.
        binary: True when ``descriptors`` are packed bits (matched by Hamming distance).
    """

    keypoints: Tensor
    descriptors: Tensor
    points: Tensor
    valid: Tensor
    sigma_px: Tensor
    K: Tensor
    image_size: tuple[int, int]
    binary: bool = True

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])

    @property
    def num_valid(self) -> int:
        """Number of keypoints with a 3D point."""
        return int(self.valid.sum())

    def to(self, device) -> FrameFeatures:
        """A copy on ``device``."""
        return replace(self, keypoints=self.keypoints.to(device), descriptors=self.descriptors.to(device),
                       points=self.points.to(device), valid=self.valid.to(device),
                       sigma_px=self.sigma_px.to(device), K=self.K.to(device))


def bucket_keypoints(xy: np.ndarray, response: np.ndarray, image_size: tuple[int, int], rows: int,
                     cols: int, max_keep: int) -> np.ndarray:
    """Indices of at most ``max_keep`` keypoints spread over a ``rows x cols`` grid.

    All cells' best (by response) come first, then all second-best, and so on.

    Args:
        xy: ``(N, 2)`` pixel coordinates.
        response: ``(N,)`` detector scores (higher is better).

    Returns:
        ``(M,)`` int64 indices, ``M = min(N, max_keep)``.

    Example:
        >>> xy = np.array([[1., 1.], [2., 2.], [90., 90.]])
        >>> bucket_keypoints(xy, np.array([3., 2., 1.]), (100, 100), 2, 2, 2).tolist()
        [0, 2]
    """
    n = xy.shape[0]
    if n == 0:
        return np.zeros(0, np.int64)
    H, W = image_size
    cx = np.clip((xy[:, 0] * cols / W).astype(np.int64), 0, cols - 1)
    cy = np.clip((xy[:, 1] * rows / H).astype(np.int64), 0, rows - 1)
    cell = cy * cols + cx
    order = np.lexsort((-response, cell))  # by cell, then strongest first
    sorted_cell = cell[order]
    first = np.searchsorted(sorted_cell, sorted_cell, side="left")
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n) - first
    keep = np.lexsort((-response, rank))[:max_keep]
    return keep.astype(np.int64)


def _to_numpy(x: ArrayLike, name: str) -> np.ndarray:
    if isinstance(x, Tensor):
        x = x.detach().cpu().numpy()
    if not isinstance(x, np.ndarray):
        raise TypeError(f"{name} must be a numpy array or torch tensor, got {type(x).__name__}")
    return x


def _detect(gray: np.ndarray, config: FeatureConfig):
    """OpenCV keypoints and descriptors of a grey image, bucketed."""
    if config.detector == "orb":
        describer = cv2.ORB_create(nfeatures=config.detect_features, scaleFactor=config.orb_scale_factor,
                                   nlevels=config.orb_levels, fastThreshold=config.fast_threshold)
    else:  # "sift" (FeatureConfig checks the name)
        describer = cv2.SIFT_create(nfeatures=config.detect_features)
    kps = describer.detect(gray, None)
    xy = np.array([k.pt for k in kps], np.float32)
    resp = np.array([k.response for k in kps], np.float32)
    keep = bucket_keypoints(xy, resp, gray.shape, config.grid_rows, config.grid_cols, config.max_features)
    kps = [kps[i] for i in keep]
    kps, desc = describer.compute(gray, kps)
    return (kps, desc) if desc is not None and len(kps) else ([], None)


def is_binary_detector(detector: str) -> bool:
    """Whether ``FeatureConfig.detector`` gives packed binary descriptors (matched by Hamming distance)."""
    return detector == "orb"


def extract_features(rgb: ArrayLike, depth: ArrayLike, K: ArrayLike,
                     config: FeatureConfig | None = None) -> FrameFeatures:
    """Detect, describe and back-project keypoints of one RGB-D frame.

    Args:
        rgb: ``(H, W, 3)`` uint8 RGB image (numpy or torch).
        depth: ``(H, W)`` float depth in metres, ``0`` or NaN where invalid.
        K: ``(3, 3)`` intrinsics.
        config: detection settings (default :class:`FeatureConfig`).

    Returns:
        :class:`FrameFeatures` on the CPU; ``N = 0`` for a textureless image.

    Raises:
        ValueError: for an image, depth or K of the wrong shape or type.
    """
    config = config or FeatureConfig()
    rgb = _to_numpy(rgb, "rgb")
    depth = _to_numpy(depth, "depth")
    K_np = _to_numpy(K, "K").astype(np.float64)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be an (H, W, 3) uint8 image, got shape {rgb.shape} dtype {rgb.dtype}")
    if depth.shape != rgb.shape[:2]:
        raise ValueError(f"depth must have shape {rgb.shape[:2]} (the rgb's (H, W)), got {depth.shape}")
    if K_np.shape != (3, 3):
        raise ValueError(f"K must have shape (3, 3), got {K_np.shape}")
    H, W = depth.shape
    gray = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    s = float(config.image_scale)
    if s != 1.0:
        gray = cv2.resize(gray, (max(1, round(W * s)), max(1, round(H * s))), interpolation=cv2.INTER_AREA)
    kps, desc = _detect(gray, config)
    binary = is_binary_detector(config.detector)
    dim = 32 if binary else 128
    K_t = torch.from_numpy(K_np)
    if len(kps) == 0:
        return FrameFeatures(
            keypoints=torch.zeros(0, 2), descriptors=torch.zeros(0, dim, dtype=torch.uint8 if binary
                                                                 else torch.float32),
            points=torch.zeros(0, 3), valid=torch.zeros(0, dtype=torch.bool), sigma_px=torch.zeros(0),
            K=K_t, image_size=(H, W), binary=binary)
    xy = np.array([k.pt for k in kps], np.float32)
    if binary:
        octave = np.array([k.octave for k in kps], np.float32)
        sigma = config.keypoint_sigma_px * config.orb_scale_factor ** octave
        desc_t = torch.from_numpy(np.ascontiguousarray(desc, dtype=np.uint8))
    else:
        octave = np.array([k.octave & 0xFF for k in kps], np.int64)
        octave = np.where(octave >= 128, octave - 256, octave)
        sigma = config.keypoint_sigma_px * 2.0 ** np.maximum(octave, 0).astype(np.float32)
        d = desc.astype(np.float32)
        d = np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), 1e-12))  # RootSIFT: unit L2 norm
        desc_t = torch.from_numpy(np.ascontiguousarray(d))
    if s != 1.0:
        # pixel centres: x_full = (x_small + 0.5) / s - 0.5
        xy = (xy + 0.5) / s - 0.5
        sigma = sigma / s
    depth_t = torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))
    if config.rgb_intrinsics is not None:
        # unregistered colour camera: warp the depth into it and lift there (its frame is the one tracked)
        fx, fy, cx, cy = config.rgb_intrinsics
        K_rgb = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
        depth_t = register_depth_to_color(depth_t, K_t, K_rgb, rig_pose(config.rgb_from_depth_translation),
                                          (H, W), min_depth=0.0)
        K_t = K_rgb
    kp_t = torch.from_numpy(xy)
    points, valid = backproject(kp_t, depth_t, K_t, config.min_depth, config.max_depth,
                                config.depth_window_radius, config.max_depth_jump)
    return FrameFeatures(keypoints=kp_t, descriptors=desc_t, points=points, valid=valid,
                         sigma_px=torch.from_numpy(np.asarray(sigma, np.float32)), K=K_t,
                         image_size=(H, W), binary=binary)
