"""Open a sequence folder (TUM RGB-D, 7-Scenes) or a ROS bag as the reader of its layout, detected from its files."""
from __future__ import annotations

import os
from pathlib import Path

from slam.io.rosbag import BAG_OPTIONS, RosbagSequence, is_rosbag
from slam.io.sequence import DatasetError, DatasetNotFoundError, RGBDSequence
from slam.io.sevenscenes import SevenScenesSequence
from slam.io.tum import TUMSequence

__all__ = ["open_sequence"]


def open_sequence(path: str | os.PathLike, camera: str | None = None, K=None, **kwargs) -> RGBDSequence:
    """Open a TUM RGB-D folder (``rgb.txt``, ``depth.txt``), a 7-Scenes folder (``frame-XXXXXX.color.*``) or a ROS
    bag (a ROS1 ``.bag`` file or a ROS2 folder; it alone takes ``rgb_topic``, ``depth_topic``, ``camera_info_topic``
    and ``groundtruth``) as its reader (:class:`~slam.io.tum.TUMSequence`, ...), detecting the layout.

    Args:
        path: the sequence folder.
        camera: TUM only: ``"fr1"``, ``"fr2"``, ``"fr3"`` or ``"ros"`` (default: from the folder name); a
            7-Scenes folder refuses it (give ``K``).
        K: ``(3, 3)`` intrinsics overriding the dataset's (``--intrinsics``).
        **kwargs: passed to the reader (both take ``depth_scale``, depth units per metre, and
            ``check_units=False``, which skips :func:`~slam.io.sequence.check_depth_units` for a scene nearer
            than 0.5 m or farther than 20 m).

    Raises:
        DatasetNotFoundError: the folder does not exist.
        DatasetError: the folder is not a sequence of either layout (the message says what was
            expected), or the reader rejects it.
    """
    root = Path(path).expanduser()
    if not root.exists():
        raise DatasetNotFoundError(root, "sequence folder does not exist")
    if is_rosbag(root):
        return RosbagSequence(root, camera=camera, K=K, **kwargs)
    given = [flag for key, flag in BAG_OPTIONS.items() if kwargs.pop(key, None) is not None]
    if given:
        raise DatasetError(root, f"{', '.join(given)} appl{'ies' if len(given) == 1 else 'y'} to a ROS bag "
                                 "(a .bag file or a ROS2 bag folder); a sequence folder's ground truth is its own")
    if not root.is_dir():
        raise DatasetError(root, "expected a sequence folder, a ROS1 .bag file or a ROS2 bag folder, got a file")
    if (root / "rgb.txt").is_file() or (root / "depth.txt").is_file():
        return TUMSequence(root, camera=camera, K=K, **kwargs)
    if any(name.startswith("frame-") and ".color." in name for name in os.listdir(root)):
        if camera is not None:
            raise DatasetError(root, f"camera={camera!r} applies to TUM sequences only; give a 7-Scenes folder's "
                                     "intrinsics with --intrinsics FX FY CX CY (K= in Python)")
        return SevenScenesSequence(root, K=K, **kwargs)
    subfolders: list[str] = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("seq-"))
    if subfolders:
        raise DatasetError(
            root, f"this looks like a 7-Scenes scene folder; open one of its sequences, e.g. {root / subfolders[0]}"
        )
    raise DatasetError(
        root,
        "not an RGB-D sequence folder: expected TUM RGB-D files (rgb.txt, depth.txt, optional groundtruth.txt) "
        "or 7-Scenes frames (frame-000000.color.png|jpg, frame-000000.depth.png, frame-000000.pose.txt)",
    )
