"""Decoding colour and depth images: every failure raises :class:`FrameReadError` carrying the path, at read
time (``sequence[i]``), so a SLAM run can skip the frame with a warning."""
from __future__ import annotations

import os

import cv2
import numpy as np

__all__ = ["FrameReadError", "depth_to_metres", "read_depth_raw", "read_rgb"]


class FrameReadError(RuntimeError):
    """One frame's image could not be read: missing, not decodable, wrong type or size.

    Attributes:
        path: the offending file.
        reason: a short explanation (also in the message).
    """

    def __init__(self, path: str, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


def decode_image(path: str, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    # read + imdecode rather than cv2.imread: tells "missing" from "undecodable", refuses a truncated JPEG
    # (imread fills the rest with grey) and handles non-ASCII paths
    try:
        buf = np.fromfile(path, dtype=np.uint8)
    except FileNotFoundError:
        raise FrameReadError(path, "file does not exist") from None
    except OSError as e:  # a folder, no permission, ...
        raise FrameReadError(path, f"cannot read file ({e.__class__.__name__}: {e})") from None
    except ValueError as e:  # a name no file can have (e.g. a NUL byte from a corrupted list file)
        raise FrameReadError(repr(path), f"not a valid file name ({e})") from None
    image = cv2.imdecode(buf, flags) if buf.size else None
    if image is None:
        raise FrameReadError(path, "not a decodable image (empty or corrupt file)")
    return image


def read_rgb(path: str) -> np.ndarray:
    """Read a colour image as RGB (grey replicated to three channels, alpha dropped).

    Args:
        path: image file (any format OpenCV decodes: PNG, JPEG, ...).

    Returns:
        ``(H, W, 3)`` uint8, RGB channel order.

    Raises:
        FrameReadError: missing file, undecodable data, or not 8-bit.
    """
    image = decode_image(os.fspath(path))
    if image.dtype != np.uint8:
        raise FrameReadError(path, f"colour image must be 8-bit, got {image.dtype}")
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    if image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    raise FrameReadError(path, f"unsupported colour image shape {image.shape}")


def read_depth_raw(path: str, expected_shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a single-channel 16-bit depth image without scaling.

    Args:
        path: a 16-bit PNG (TUM: 5000 units per metre; 7-Scenes: millimetres).
        expected_shape: ``(H, W)`` the depth must have (the colour image's); None skips the check.

    Returns:
        ``(H, W)`` uint16 raw values.

    Raises:
        FrameReadError: missing file, undecodable data, not 16-bit single channel, or wrong size.
    """
    depth = decode_image(os.fspath(path))
    if depth.dtype != np.uint16:
        raise FrameReadError(path, f"depth image must be 16-bit (uint16), got {depth.dtype}")
    if depth.ndim != 2:
        raise FrameReadError(path, f"depth image must have one channel, got shape {depth.shape}")
    if expected_shape is not None and tuple(depth.shape) != tuple(expected_shape):
        raise FrameReadError(
            path, f"depth image is {depth.shape[1]}x{depth.shape[0]} but the colour image is "
            f"{expected_shape[1]}x{expected_shape[0]}"
        )
    return depth


def depth_to_metres(raw: np.ndarray, scale: float, invalid_values: tuple[int, ...] = (0,)) -> np.ndarray:
    """Convert raw 16-bit depth to metres (a true division keeps exact values exact: 5000 -> 1.0).

    Args:
        raw: ``(H, W)`` uint16.
        scale: raw units per metre (TUM 5000, 7-Scenes 1000).
        invalid_values: raw values meaning "no measurement"; they become 0.0.

    Returns:
        ``(H, W)`` float32 metres, 0.0 where invalid.

    Example:
        >>> depth_to_metres(np.array([[0, 5000, 65535]], dtype=np.uint16), 5000.0, (0, 65535))
        array([[0., 1., 0.]], dtype=float32)
    """
    depth = raw.astype(np.float32)
    np.divide(depth, np.float32(scale), out=depth)
    for value in invalid_values:
        if value != 0:  # 0 already maps to 0.0
            depth[raw == value] = 0.0
    return depth
