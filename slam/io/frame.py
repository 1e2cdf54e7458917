"""The frame record every dataset reader yields, and the checks that make a wrong frame an error.

An :class:`RGBDFrame` is checked when it is built (:func:`check_frame`): a wrong type, shape or unit raises a
``TypeError`` / ``ValueError`` saying what was expected. Types and units (what the readers produce, and what
a caller streaming its own frames must give):

* ``rgb``: numpy ``(H, W, 3)`` uint8, **RGB** channel order (OpenCV's ``imread`` gives BGR: use
  ``cv2.cvtColor(img, cv2.COLOR_BGR2RGB)``; a greyscale image: ``cv2.cvtColor(g, cv2.COLOR_GRAY2RGB)``).
* ``depth``: numpy ``(H, W)`` float32 **metres**, 0.0 where there is no measurement. Converted silently:
  float64 (to float32) and NaN / +inf (to 0.0, the ROS convention for "no measurement"). Refused: integer
  depth (divide by your sensor's depth scale first: TUM 5000, Kinect millimetres 1000), negative values,
  and float depth whose median valid value is beyond :data:`MAX_DEPTH_MEDIAN` metres (millimetres or raw
  units by mistake).
* ``K``: ``(3, 3)`` float64 pinhole intrinsics ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` with finite
  entries and ``fx, fy > 0``. A nested list or an integer array is converted silently.
* ``pose_gt``: None or ``(7,)`` float64 ``[t, q_xyzw]`` camera-to-world; a quaternion of any non-zero
  norm is normalised (:func:`slam.input_checks.unit_quaternions`).

Example:
    >>> K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    >>> f = RGBDFrame(0, 0.0, np.zeros((480, 640, 3), np.uint8), np.ones((480, 640), np.float32), K)
    >>> f.shape, f.K.dtype
    ((480, 640), dtype('float64'))
    >>> RGBDFrame(0, 0.0, f.rgb, np.full((480, 640), 1500, np.uint16), K)
    Traceback (most recent call last):
    ...
    TypeError: depth must be float32 metres, got uint16 (480, 640); divide by your depth scale (TUM 5000, ...
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from slam.input_checks import MAX_COORDINATE, unit_quaternions

__all__ = ["DEPTH_MEDIAN_RANGE", "MAX_DEPTH_MEDIAN", "RGBDFrame", "check_frame", "check_intrinsics",
           "median_valid_depth"]

# metres: no RGB-D sensor's typical (median) depth is beyond this, while depth in millimetres (~1000-4000)
# or TUM's raw units (~5000-20000) always is
MAX_DEPTH_MEDIAN = 100.0
# metres: the median valid depth of an RGB-D camera's view of a scene (sensors measure from 0.3-0.5 m to ~20 m)
DEPTH_MEDIAN_RANGE = (0.5, 20.0)


def _not_torch(x, name: str, expected: str) -> None:
    if type(x).__module__.startswith("torch"):
        raise TypeError(f"{name} must be a numpy array {expected}, got a torch tensor; pass x.cpu().numpy()")


def check_intrinsics(K, name: str = "K") -> np.ndarray:
    """``K`` as a ``(3, 3)`` float64 pinhole matrix, or a ``TypeError`` / ``ValueError`` naming ``name``.

    Args:
        K: a ``(3, 3)`` array or nested list ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``.
        name: how the error names it (e.g. a file name).

    Returns:
        A float64 copy.
    """
    _not_torch(K, name, "(3, 3) float64")
    try:
        M = np.array(K, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a (3, 3) array of numbers, got {type(K).__name__}") from None
    if M.shape != (3, 3):
        raise ValueError(f"{name} must have shape (3, 3), got {M.shape}")
    if not np.isfinite(M).all():
        raise ValueError(f"{name} has a non-finite entry: {M.tolist()}")
    if not (M[0, 0] > 0 and M[1, 1] > 0):
        raise ValueError(f"{name} must have focal lengths fx = K[0, 0] > 0 and fy = K[1, 1] > 0, got "
                         f"{M[0, 0]:g} and {M[1, 1]:g}")
    if M[1, 0] != 0 or M[2, 0] != 0 or M[2, 1] != 0 or M[2, 2] != 1:
        raise ValueError(f"{name} must be a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {M.tolist()}")
    if np.abs(M[:2, 2]).max() > 1e6:
        raise ValueError(f"{name} has a principal point ({M[0, 2]:g}, {M[1, 2]:g}) beyond 1e6 pixels")
    return M


def _check_rgb(rgb) -> np.ndarray:
    _not_torch(rgb, "rgb", "(H, W, 3) uint8")
    if not isinstance(rgb, np.ndarray):
        raise TypeError(f"rgb must be a numpy array (H, W, 3) uint8, got {type(rgb).__name__}")
    if rgb.ndim == 2 or rgb.ndim == 3 and rgb.shape[2] == 1:
        raise ValueError(f"rgb must be (H, W, 3) RGB, got a greyscale image {rgb.shape}; convert it with "
                         "cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)")
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise ValueError(f"rgb must have shape (H, W, 3), got {rgb.shape}")
    if rgb.dtype != np.uint8:
        hint = " (floats in [0, 1]: (img * 255).round().astype(np.uint8))" if rgb.dtype.kind == "f" else ""
        raise TypeError(f"rgb must be uint8 in [0, 255], got {rgb.dtype}{hint}")
    return rgb


def _check_depth(depth, shape) -> np.ndarray:
    _not_torch(depth, "depth", "(H, W) float32 metres")
    if not isinstance(depth, np.ndarray):
        raise TypeError(f"depth must be a numpy array (H, W) float32 metres, got {type(depth).__name__}")
    if depth.dtype.kind in "iub":
        raise TypeError(f"depth must be float32 metres, got {depth.dtype} {depth.shape}; divide by your depth scale "
                        "(TUM 5000, Kinect millimetres 1000): depth.astype(np.float32) / scale")
    if depth.dtype.kind != "f":
        raise TypeError(f"depth must be float32 metres, got {depth.dtype}")
    if depth.ndim == 3 and depth.shape[2] == 1:
        depth = depth[..., 0]
    if depth.ndim != 2:
        raise ValueError(f"depth must have shape (H, W), got {depth.shape}")
    if depth.shape != shape:
        raise ValueError(f"depth is {depth.shape[1]}x{depth.shape[0]} but rgb is {shape[1]}x{shape[0]}; expected "
                         "registered images of one size")
    depth = np.asarray(depth, dtype=np.float32)
    lo, hi = float(depth.min()), float(depth.max())
    if math.isnan(lo) or math.isnan(hi) or hi == math.inf:  # ROS marks "no measurement" so: 0.0 here
        depth = np.where(np.isfinite(depth), depth, np.float32(0.0))
        lo, hi = float(depth.min()), float(depth.max())
    if lo < 0:
        raise ValueError(f"depth has negative values (min {lo:g}); expected metres >= 0 with 0 for no measurement")
    if hi > MAX_DEPTH_MEDIAN:
        med = median_valid_depth(depth)
        if med > MAX_DEPTH_MEDIAN:
            raise ValueError(f"depth must be metres, but its median valid value is {med:g} (beyond "
                             f"{MAX_DEPTH_MEDIAN:g} m): millimetres or raw sensor units? divide by your depth scale "
                             "(TUM 5000, Kinect millimetres 1000)")
    return depth


def median_valid_depth(depth: np.ndarray) -> float:
    """The median of the valid (> 0) values of ``depth (H, W)`` on every 4th row and column; 0.0 when nothing
    is valid."""
    sample = np.asarray(depth)[::4, ::4]
    valid = sample[sample > 0]
    return float(np.median(valid)) if valid.size else 0.0


def _check_pose(pose) -> Optional[np.ndarray]:
    if pose is None:
        return None
    _not_torch(pose, "pose_gt", "(7,) float64")
    p = np.array(pose, dtype=np.float64).reshape(-1)
    if p.shape != (7,):
        raise ValueError(f"pose_gt must have shape (7,) [tx, ty, tz, qx, qy, qz, qw], got {np.shape(pose)}")
    if not np.isfinite(p).all():
        raise ValueError(f"pose_gt has a non-finite value: {p.tolist()} (use None for an unknown pose)")
    if np.abs(p[:3]).max() > MAX_COORDINATE:
        raise ValueError(f"pose_gt has a translation beyond {MAX_COORDINATE:.0e} m: {p[:3].tolist()}")
    q, zero = unit_quaternions(p[None, 3:])
    if zero[0]:
        raise ValueError(f"pose_gt has a zero quaternion {p[3:].tolist()}; expected [qx, qy, qz, qw] of a rotation")
    p[3:] = q[0]
    return p


def check_frame(frame: RGBDFrame) -> RGBDFrame:
    """Check (and convert where lossless, see the module docstring) every field of ``frame`` in place.

    Returns:
        ``frame``.

    Raises:
        TypeError: a field of the wrong type (a torch tensor, integer depth, float colour, ...).
        ValueError: a field of the wrong shape or with values out of their range.
    """
    if isinstance(frame.index, bool) or not isinstance(frame.index, (int, np.integer)):
        raise TypeError(f"index must be an int, got {type(frame.index).__name__}")
    if isinstance(frame.timestamp, bool) or not isinstance(frame.timestamp, (int, float, np.integer, np.floating)):
        raise TypeError(f"timestamp must be a number of seconds, got {type(frame.timestamp).__name__}")
    t = float(frame.timestamp)
    if not math.isfinite(t):
        raise ValueError(f"timestamp must be finite, got {t}")
    frame.index, frame.timestamp = int(frame.index), t
    frame.rgb = _check_rgb(frame.rgb)
    frame.depth = _check_depth(frame.depth, frame.rgb.shape[:2])
    frame.K = check_intrinsics(frame.K)
    frame.pose_gt = _check_pose(frame.pose_gt)
    return frame


@dataclass
class RGBDFrame:
    """One registered RGB-D frame (checked on construction by :func:`check_frame`).

    Attributes:
        index: position of the frame in its sequence (0-based, input order).
        timestamp: seconds (TUM: the rgb timestamp; 7-Scenes: ``index / 30``).
        rgb: ``(H, W, 3)`` uint8, RGB channel order.
        depth: ``(H, W)`` float32 metres; **0.0 marks an invalid pixel** (never NaN).
        K: ``(3, 3)`` float64 pinhole intrinsics of the (registered) camera.
        pose_gt: ``(7,)`` float64 camera-to-world ground truth ``[t, q_xyzw]``, or None if unknown.
        rgb_path: the file the colour image came from ("" for generated frames).
        depth_path: the file the depth image came from ("" for generated frames).
    """

    index: int
    timestamp: float
    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    pose_gt: Optional[np.ndarray] = None
    rgb_path: str = ""
    depth_path: str = ""

    def __post_init__(self) -> None:
        check_frame(self)

    @property
    def shape(self) -> tuple:
        """``(H, W)`` of the images."""
        return tuple(self.depth.shape)
