"""TUM RGB-D sequences (Sturm et al. 2012): ``rgb.txt``, ``depth.txt``, optional ``groundtruth.txt``.

* Frames are the rgb/depth pairs associated as TUM's ``associate.py`` does (nearest timestamps less than
  0.02 s apart, greedy one-to-one), in rgb-time order; a frame's timestamp is its rgb stamp. rgb entries
  without a depth entry are not frames (logged at INFO).
* Ground truth of a frame: a ``groundtruth.txt`` pose less than 0.02 s from its rgb stamp, by the same greedy
  one-to-one association as TUM's ``evaluate_ate.py`` (no interpolation); a subset of the frames
  (``seq[::2]``) is paired among itself. Ground truth that matches no frame is kept as read
  (:attr:`TUMSequence.groundtruth_trajectory`).
* Timestamps are seconds; milli-, micro- or nanoseconds (:func:`slam.input_checks.timestamp_unit`) are
  converted with one warning; frame numbers are a :class:`DatasetError`.
* Depth: 16-bit PNG, ``depth_scale`` (5000) units per metre, 0 = invalid -> float32 metres; the first frames'
  depth is checked against the scale (:func:`slam.io.sequence.check_depth_units`).
* Intrinsics: ``K`` if given, else ``camera`` (``fr1``/``fr2``/``fr3``/``ros``), else a ``calibration.txt``
  in the folder (``fx fy cx cy`` [+ 5 distortion coefficients]), else inferred from the folder name (a
  symlink's own name first, then its target's), else the ROS default with a warning. ``undistort=True``
  remaps both images with the fr1/fr2 distortion (depth by nearest neighbour).

List files: ``# comments``, blank lines, ``timestamp filename`` per line, exactly these two fields (separated
by spaces, tabs or a comma); an uncommented ``timestamp filename`` header is skipped; a repeated timestamp
keeps its last line, as TUM's scripts do.
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from slam.io.associate import TUM_MAX_DIFFERENCE, associate
from slam.input_checks import TIME_UNITS, timestamp_unit
from slam.io.frame import RGBDFrame, check_intrinsics
from slam.io.images import depth_to_metres, read_depth_raw, read_rgb
from slam.io.sequence import (DatasetError, DatasetNotFoundError, RGBDSequence, check_depth_scale, check_depth_units,
                              read_dataset_lines)
from slam.io.trajectory import Trajectory, data_lines, read_tum_trajectory

__all__ = [
    "TUM_CAMERAS",
    "TUM_DEPTH_FACTOR",
    "TUMCamera",
    "TUMSequence",
    "TimeAssociatedSequence",
    "camera_from_name",
    "read_calibration_file",
    "read_file_list",
    "tum_camera",
]

logger = logging.getLogger(__name__)

# Raw depth units per metre in every TUM RGB-D sequence.
TUM_DEPTH_FACTOR = 5000.0


@dataclass(frozen=True)
class TUMCamera:
    """Pinhole intrinsics (pixels) and OpenCV distortion ``(k1, k2, p1, p2, k3)``."""

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def K(self) -> np.ndarray:
        """``(3, 3)`` float64."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


# The TUM RGB-D calibration (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats).
TUM_CAMERAS: dict[str, TUMCamera] = {
    "fr1": TUMCamera(517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "fr2": TUMCamera(520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "fr3": TUMCamera(535.4, 539.2, 320.1, 247.6),
    "ros": TUMCamera(525.0, 525.0, 319.5, 239.5),
}
_ALIASES = {"freiburg1": "fr1", "freiburg2": "fr2", "freiburg3": "fr3", "default": "ros", "ros_default": "ros"}
_NAME_RE = re.compile(r"(?<![a-z])(?:freiburg|fr)[_-]?([123])(?![0-9])")


def tum_camera(name: str) -> TUMCamera:
    """The calibration called ``fr1``/``freiburg1``, ``fr2``, ``fr3`` or ``ros``/``default`` (any case).

    Raises:
        ValueError: an unknown name.

    Example:
        >>> tum_camera("freiburg2").fx, tum_camera("fr4")
        Traceback (most recent call last):
        ...
        ValueError: unknown TUM camera 'fr4'; expected one of fr1, fr2, fr3, ros
    """
    key = _ALIASES.get(name.lower(), name.lower()) if isinstance(name, str) else None
    if key not in TUM_CAMERAS:
        raise ValueError(f"unknown TUM camera {name!r}; expected one of fr1, fr2, fr3, ros")
    return TUM_CAMERAS[key]


def camera_from_name(folder_name: str) -> str | None:
    """``"fr1"``/``"fr2"``/``"fr3"`` from a name such as ``rgbd_dataset_freiburg1_xyz`` or ``fr3_office``.

    Example:
        >>> camera_from_name("rgbd_dataset_freiburg2_desk"), camera_from_name("fr1_xyz"), camera_from_name("frames")
        ('fr2', 'fr1', None)
    """
    m = _NAME_RE.search(folder_name.lower())
    return f"fr{m.group(1)}" if m else None


def read_calibration_file(path: Path) -> TUMCamera:
    """A camera from ``calibration.txt``: the first non-comment line ``fx fy cx cy [k1 k2 p1 p2 k3]``.

    Raises:
        DatasetError: a malformed file (with the line number), non-finite values or a focal length <= 0.
    """
    for number, raw in enumerate(read_dataset_lines(path), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        try:
            values = [float(v) for v in line.replace(",", " ").split()]
        except ValueError:
            raise DatasetError(path, f"expected 'fx fy cx cy [k1 k2 p1 p2 k3]', got {line!r}", number) from None
        if len(values) not in (4, 9):
            raise DatasetError(path, f"expected 4 or 9 numbers 'fx fy cx cy [k1 k2 p1 p2 k3]', got {len(values)}",
                               number)
        if not np.isfinite(values).all():
            raise DatasetError(path, f"non-finite value in {line!r}", number)
        dist = tuple(values[4:]) if len(values) == 9 else (0.0,) * 5
        cam = TUMCamera(*values[:4], distortion=dist)
        try:
            check_intrinsics(cam.K, "the camera")
        except ValueError as e:
            raise DatasetError(path, str(e), number) from None
        return cam
    raise DatasetError(path, "no 'fx fy cx cy' line")


def _in_seconds(stamps: np.ndarray, path: Path, converted: list[str], frames: np.ndarray | None = None) -> np.ndarray:
    """``stamps`` in seconds: milli-, micro- and nanoseconds (:func:`timestamp_unit`) are divided (``converted``
    records which file); frame numbers are a :class:`DatasetError`. Given the frames' stamps in seconds, the
    unit that puts ``stamps`` within their span wins (fast motion capture in ns is spaced like microseconds)."""
    unit, per_second, spacing = timestamp_unit(stamps)
    if frames is not None and len(frames) and len(stamps):
        lo, hi = float(frames.min()), float(frames.max())
        overlap = [(name, u) for name, u in TIME_UNITS.items() if stamps.min() / u <= hi and stamps.max() / u >= lo]
        if len(overlap) == 1:
            unit, per_second = overlap[0]
    if per_second is None:
        raise DatasetError(path, "the timestamps are frame numbers (whole numbers 1 apart), not seconds: write each "
                                 "frame's time in seconds (its number divided by the frame rate, e.g. / 30 at 30 Hz)")
    if per_second != 1.0:
        converted.append(f"{path.name} in {unit} ({per_second / spacing:.3g} Hz)")
        return stamps / per_second
    return stamps


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """Read a TUM list file (``rgb.txt``, ``depth.txt``): ``timestamp filename`` per line, exactly two fields.

    Returns:
        timestamps ``(N,)`` float64 and the N file names (relative to the sequence folder), in file
        order, a repeated timestamp keeping its last line.

    Raises:
        DatasetNotFoundError: the file does not exist.
        DatasetError: a malformed line (with its number) or no entries at all.
    """
    if not path.is_file():
        raise DatasetNotFoundError(path, "list file does not exist")
    entries: dict[float, str] = {}  # timestamp -> file name
    for number, line, fields in data_lines(read_dataset_lines(path), lambda n, m: DatasetError(path, m, n)):
        if len(fields) != 2:
            raise DatasetError(path, f"expected 2 fields 'timestamp filename', got {len(fields)} in {line!r} "
                                     "(a file name cannot hold spaces or commas)", number)
        try:
            stamp = float(fields[0])
        except ValueError:
            raise DatasetError(path, f"timestamp is not a number in {line!r}", number) from None
        if not np.isfinite(stamp):
            raise DatasetError(path, f"non-finite timestamp in {line!r}", number)
        if stamp in entries:
            logger.warning("%s:%d: repeated timestamp %r, keeping this line", path, number, stamp)
            del entries[stamp]  # re-insert below so the file order follows the kept line
        entries[stamp] = fields[1]
    if not entries:
        raise DatasetError(path, "the list is empty (no 'timestamp filename' lines)")
    return np.fromiter(entries.keys(), dtype=np.float64, count=len(entries)), list(entries.values())


class TimeAssociatedSequence(RGBDSequence):
    """Stamped frames whose ground truth is a trajectory file paired with them by TUM's one-to-one association
    (``evaluate_ate.py``): a TUM folder's ``groundtruth.txt``, a ROS bag's ``--ground-truth``.

    A subclass sets ``_timestamps`` ``(N,)`` seconds, ``_gt_trajectory`` (a
    :class:`~slam.io.trajectory.Trajectory` or None), ``max_difference`` (seconds) and then
    ``_gt = self._associate_groundtruth(self._timestamps)``.
    """

    _gt: np.ndarray
    _gt_trajectory: Trajectory | None = None
    max_difference: float = TUM_MAX_DIFFERENCE

    @property
    def groundtruth_trajectory(self) -> Trajectory | None:
        """The ground-truth poses as read, None without a file; :attr:`groundtruth` holds those paired with frames."""
        return self._gt_trajectory

    def _associate_groundtruth(self, stamps: np.ndarray) -> np.ndarray:
        """``(N, 7)`` ground truth of frames at ``stamps (N,)``, NaN rows where none is within ``max_difference``."""
        gt = np.full((len(stamps), 7), np.nan)
        if self._gt_trajectory is not None and len(stamps):
            a, b = associate(stamps, self._gt_trajectory.timestamps, self.max_difference)
            gt[a.numpy()] = self._gt_trajectory.poses.numpy()[b.numpy()]
        return gt

    def _groundtruth_of(self, indices: np.ndarray) -> np.ndarray:
        # the association is one-to-one: the subset's frames are paired among themselves
        return self._associate_groundtruth(self._timestamps[indices])

    def _groundtruth_array(self) -> np.ndarray:
        return self._gt


class TUMSequence(TimeAssociatedSequence):
    """A TUM RGB-D sequence folder, read lazily.

    Args:
        root: the folder holding ``rgb.txt`` and ``depth.txt`` (and optionally ``groundtruth.txt``).
        camera: ``"fr1"``, ``"fr2"``, ``"fr3"`` or ``"ros"``; None: ``calibration.txt`` if present, else
            inferred from the folder name. ``camera_name`` records the choice.
        K: ``(3, 3)`` intrinsics overriding ``camera``.
        max_difference: association tolerance in seconds (TUM: 0.02).
        undistort: remap colour (bilinear) and depth (nearest) with the camera's distortion.
        depth_scale: depth units per metre (default TUM's 5000; 1000 for millimetre PNGs).
        check_units: check the first frames' median depth at ``depth_scale``.

    Raises:
        DatasetNotFoundError: missing folder, ``rgb.txt`` or ``depth.txt``.
        DatasetError: malformed or empty lists, no rgb/depth pair within ``max_difference``, an unknown
            ``camera``, frame numbers for timestamps, depth whose median is not a camera's at ``depth_scale``.
        TrajectoryFormatError: a malformed ``groundtruth.txt`` line.

    Example:
        >>> seq = TUMSequence("rgbd_dataset_freiburg1_xyz")  # doctest: +SKIP
        >>> seq[0].rgb.shape, seq[0].depth.dtype  # doctest: +SKIP
        ((480, 640, 3), dtype('float32'))
    """

    depth_scale = TUM_DEPTH_FACTOR

    def __init__(self, root, camera: str | None = None, K=None, max_difference: float = TUM_MAX_DIFFERENCE,
                 undistort: bool = False, depth_scale: float | None = None, check_units: bool = True):
        self.root = Path(root).expanduser()
        if not self.root.is_dir():
            raise DatasetNotFoundError(self.root, "sequence folder does not exist")
        if depth_scale is not None:
            self.depth_scale = check_depth_scale(depth_scale, self.root)
        # the name as given (a symlink's may carry the camera), the target's where it has none ("..")
        given = self.root.absolute().name
        self.name = given if given not in ("", ".", "..") else self.root.resolve().name
        rgb_stamps, rgb_names = read_file_list(self.root / "rgb.txt")
        depth_stamps, depth_names = read_file_list(self.root / "depth.txt")
        converted: list[str] = []  # lists whose timestamps were not seconds (one notice for all)
        rgb_stamps = _in_seconds(rgb_stamps, self.root / "rgb.txt", converted)
        depth_stamps = _in_seconds(depth_stamps, self.root / "depth.txt", converted)
        i, j = associate(rgb_stamps, depth_stamps, max_difference)
        if i.numel() == 0:
            raise DatasetError(self.root, f"no rgb.txt and depth.txt timestamps are within {max_difference} s")
        i, j = i.numpy(), j.numpy()
        if len(i) < len(rgb_stamps):  # TUM's association leaves them out; say how many, once
            logger.info("%s: %d of %d rgb.txt entries have no depth.txt entry within %g s: not used",
                        self.root, len(rgb_stamps) - len(i), len(rgb_stamps), max_difference)
        self._timestamps = rgb_stamps[i]
        self.depth_timestamps = depth_stamps[j]
        self._rgb = [rgb_names[k] for k in i]
        self._depth = [depth_names[k] for k in j]

        self.camera_name = None
        if K is not None:
            self.K, self.distortion = check_intrinsics(K, "K"), np.zeros(5)
        elif camera is None and (self.root / "calibration.txt").is_file():
            cam = read_calibration_file(self.root / "calibration.txt")
            self.camera_name = "calibration.txt"
            self.K, self.distortion = cam.K, np.asarray(cam.distortion, dtype=np.float64)
        else:
            self.camera_name = camera if camera is not None else (camera_from_name(self.name)
                                                                  or camera_from_name(self.root.resolve().name))
            if self.camera_name is None:
                logger.warning("%s: camera not given and not in the folder name (fr1/fr2/fr3); using the ROS "
                               "default intrinsics 525, 525, 319.5, 239.5", self.root)
                self.camera_name = "ros"
            try:
                cam = tum_camera(self.camera_name)
            except ValueError as e:
                raise DatasetError(self.root, str(e)) from None
            self.K, self.distortion = cam.K, np.asarray(cam.distortion, dtype=np.float64)
        self.undistort = bool(undistort) and bool(np.any(self.distortion != 0))
        self._maps = None

        self.groundtruth_file: Path | None = self.root / "groundtruth.txt"
        self.max_difference = float(max_difference)  # the association tolerance (s), rgb-depth and ground truth
        self._gt_trajectory = None
        if self.groundtruth_file.is_file():
            gt = read_tum_trajectory(self.groundtruth_file)
            stamps = gt.timestamps.numpy()
            seconds = _in_seconds(stamps, self.groundtruth_file, converted, self._timestamps)
            self._gt_trajectory = gt if seconds is stamps else Trajectory(torch.from_numpy(seconds), gt.poses)
        else:
            self.groundtruth_file = None
        if converted:
            logger.warning("%s: timestamps of %s: converted to seconds", self.root, ", ".join(converted))
        self._gt = self._associate_groundtruth(self._timestamps)
        if check_units:
            check_depth_units(self.root, [self.root / name for name in self._depth[:10]], self.depth_scale)

    def paths(self, i: int) -> tuple[Path, Path]:
        """The colour and depth files of frame ``i``."""
        return self.root / self._rgb[i], self.root / self._depth[i]

    def _load(self, i: int) -> RGBDFrame:
        rgb_path, depth_path = self.paths(i)
        rgb = read_rgb(str(rgb_path))
        raw = read_depth_raw(str(depth_path), rgb.shape[:2])
        if self.undistort:
            rgb, raw = self._remap(rgb, raw)
        return self._frame(i, rgb, depth_to_metres(raw, self.depth_scale), self._gt[i], (rgb_path, depth_path))

    def _remap(self, rgb: np.ndarray, raw: np.ndarray):
        h, w = raw.shape
        if self._maps is None or self._maps[0].shape[:2] != (h, w):
            self._maps = cv2.initUndistortRectifyMap(self.K, self.distortion, None, self.K, (w, h), cv2.CV_16SC2)
        m1, m2 = self._maps
        return (cv2.remap(rgb, m1, m2, cv2.INTER_LINEAR),
                cv2.remap(raw, m1, m2, cv2.INTER_NEAREST))  # nearest: never blend across depth edges
