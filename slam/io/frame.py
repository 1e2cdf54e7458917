"""The frame record every dataset reader yields."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np


@dataclass
class RGBDFrame:
    """One registered RGB-D frame.

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

    @property
    def shape(self) -> tuple:
        """``(H, W)`` of the images."""
        return tuple(self.depth.shape)
