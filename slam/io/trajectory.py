"""TUM-format trajectories: ``timestamp tx ty tz qx qy qz qw`` per line."""
from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Trajectory:
    """A timed sequence of camera-to-world poses.

    Attributes:
        timestamps: ``(N,)`` float64 seconds.
        poses: ``(N, 7)`` float64 ``[tx, ty, tz, qx, qy, qz, qw]``.
    """

    timestamps: torch.Tensor
    poses: torch.Tensor

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])
