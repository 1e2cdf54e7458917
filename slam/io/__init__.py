"""Datasets and files: RGB-D sequences (TUM RGB-D, 7-Scenes) and TUM trajectory files.

``open_sequence(folder)`` detects the layout and returns an :class:`RGBDSequence`: ``len(seq)``,
``seq[i]`` (an :class:`RGBDFrame`, decoded on demand), ``seq.timestamps``, ``seq.groundtruth``, ``seq.K``;
e.g. on ``../shared/data/7scenes-redkitchen`` ``seq[0].rgb.shape == (480, 640, 3)``.

Example:
    >>> camera_from_name("rgbd_dataset_freiburg1_xyz"), TUM_CAMERAS["fr1"].fx, TUM_DEPTH_FACTOR
    ('fr1', 517.3, 5000.0)
"""
from slam.io.detect import open_sequence
from slam.io.frame import RGBDFrame, check_frame, check_intrinsics
from slam.io.images import FrameReadError, depth_to_metres, read_depth_raw, read_rgb
from slam.io.sequence import (
    DatasetError,
    DatasetNotFoundError,
    DatasetWarning,
    RGBDSequence,
    SequenceView,
)
from slam.io.sevenscenes import SevenScenesSequence
from slam.io.trajectory import Trajectory, TrajectoryFormatError, read_tum_trajectory, write_tum_trajectory
from slam.io.tum import (
    TUM_CAMERAS,
    TUM_DEPTH_FACTOR,
    TUMCamera,
    TUMSequence,
    camera_from_name,
    read_file_list,
)

__all__ = [
    "TUM_CAMERAS",
    "TUM_DEPTH_FACTOR",
    "DatasetError",
    "DatasetNotFoundError",
    "DatasetWarning",
    "FrameReadError",
    "RGBDFrame",
    "RGBDSequence",
    "SequenceView",
    "SevenScenesSequence",
    "TUMCamera",
    "TUMSequence",
    "Trajectory",
    "TrajectoryFormatError",
    "camera_from_name",
    "check_frame",
    "check_intrinsics",
    "depth_to_metres",
    "open_sequence",
    "read_depth_raw",
    "read_file_list",
    "read_rgb",
    "read_tum_trajectory",
    "write_tum_trajectory",
]
