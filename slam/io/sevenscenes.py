"""Microsoft 7-Scenes sequences (one ``seq-XX`` folder), read lazily.

Layout: ``frame-%06d.color.(png|jpg)``, ``frame-%06d.depth.png`` (16-bit millimetres, 0 and 65535
invalid), ``frame-%06d.pose.txt`` (4x4 camera-to-world, optional; rotations projected onto the nearest
rotation), optional ``camera-intrinsics.txt`` (3x3; default fx = fy = 585, cx = 320, cy = 240). Frame ``k``
is at ``k / 30`` s. Colour and depth come from two unregistered cameras: the images are given as they are
with ``K`` of the depth camera (the frame of the depth images and of the ground truth); ``attnloop-slam``
applies the Kinect v1 rig by default (:data:`slam.options.KINECT_V1_RIG`).

A pose file with non-finite entries (lost tracking) means "no ground truth" for that frame; so does one that
cannot be a pose (text, not UTF-8, not 16 numbers, a last row other than ``0 0 0 1``, a rotation block with
singular values outside ``1 +- 0.01`` or a reflection, a translation beyond
:data:`~slam.input_checks.MAX_COORDINATE`), with a :class:`~slam.io.sequence.DatasetWarning` naming the file.
``camera-intrinsics.txt`` must hold a pinhole matrix, else :class:`~slam.io.sequence.DatasetError`.
"""
from __future__ import annotations

import math
import os
import re
import warnings
from numbers import Real
from pathlib import Path

import numpy as np
import torch

from slam.input_checks import MAX_COORDINATE
from slam.io.frame import RGBDFrame, check_intrinsics
from slam.io.images import depth_to_metres, read_depth_raw, read_rgb
from slam.io.sequence import (DatasetError, DatasetNotFoundError, DatasetWarning, RGBDSequence, check_depth_scale,
                               check_depth_units, read_dataset_lines)
from slam.lie import rotmat_project, se3_from_matrix

__all__ = [
    "SEVENSCENES_DEPTH_SCALE",
    "SEVENSCENES_FPS",
    "SEVENSCENES_INVALID_DEPTH",
    "SEVENSCENES_K",
    "SevenScenesSequence",
]

# The 7-Scenes Kinect's nominal intrinsics (the dataset's documentation).
SEVENSCENES_K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])
SEVENSCENES_FPS = 30.0  # frame k is at k / 30 s
SEVENSCENES_DEPTH_SCALE = 1000.0  # millimetres
SEVENSCENES_INVALID_DEPTH = (0, 65535)

_COLOR_RE = re.compile(r"^frame-(\d+)\.color\.(png|jpg|jpeg)$", re.IGNORECASE)
_PREFERENCE = {"png": 0, "jpg": 1, "jpeg": 1}  # lossless first when both exist


# a rotation block whose singular values are further than this from 1 is not a rotation
_ROTATION_TOLERANCE = 0.01


def _read_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """The ``shape`` matrix a text file holds; :class:`DatasetError` naming the file (and line) otherwise."""
    values = []
    for number, line in enumerate(read_dataset_lines(path), start=1):
        try:
            values += [float(v) for v in line.replace(",", " ").split()]
        except ValueError:
            raise DatasetError(path, f"expected {shape[0]}x{shape[1]} numbers, got {line.strip()!r}", number) from None
    if len(values) != shape[0] * shape[1]:
        raise DatasetError(path, f"expected {shape[0] * shape[1]} numbers ({shape[0]}x{shape[1]}), got {len(values)}")
    return np.array(values, dtype=np.float64).reshape(shape)


def _pose_problems(T: np.ndarray) -> list:
    """Why each of the finite ``(N, 4, 4)`` matrices is not a camera-to-world pose (None when it is one)."""
    s = np.linalg.svd(T[:, :3, :3], compute_uv=False)
    det = np.linalg.det(T[:, :3, :3])
    out = []
    for k in range(T.shape[0]):
        if np.abs(T[k, 3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
            out.append(f"its last row is {T[k, 3].tolist()}, expected [0, 0, 0, 1]")
        elif np.abs(s[k] - 1.0).max() > _ROTATION_TOLERANCE or det[k] <= 0:
            out.append(f"its rotation block is not a rotation (singular values {np.round(s[k], 4).tolist()}, "
                       f"determinant {det[k]:.4g})")
        elif np.abs(T[k, :3, 3]).max() > MAX_COORDINATE:
            out.append(f"its translation {T[k, :3, 3].tolist()} is beyond {MAX_COORDINATE:.0e} m")
        else:
            out.append(None)
    return out


def _read_poses(root: Path, names: list, warned: set) -> np.ndarray:
    """``(N, 7)`` camera-to-world poses of the pose files ``names`` (None: no file), NaN rows where unknown; one
    warning names the files that are not a pose and are not yet in ``warned`` (added to it). Rotation blocks are
    replaced by the nearest rotation (KinectFusion's are not exactly orthonormal)."""
    Ts = np.full((len(names), 4, 4), np.nan)
    problems = []
    for i, name in enumerate(names):
        if name is not None:
            try:
                Ts[i] = _read_matrix(root / name, (4, 4))
            except DatasetError as e:
                problems.append((name, str(e)))
    ok = np.isfinite(Ts).all(axis=(1, 2))  # non-finite entries: 7-Scenes' mark of lost tracking
    for k, problem in zip(np.nonzero(ok)[0], _pose_problems(Ts[ok]) if ok.any() else []):
        if problem is not None:
            ok[k] = False
            problems.append((names[k], f"{root / names[k]}: {problem}"))
    poses = np.full((len(names), 7), np.nan)
    if ok.any():
        Tt = torch.from_numpy(np.ascontiguousarray(Ts[ok], dtype=np.float64))
        poses[ok] = se3_from_matrix(torch.cat([rotmat_project(Tt[:, :3, :3]), Tt[:, :3, 3:]], dim=-1)).numpy()
    fresh = [msg for name, msg in problems if name not in warned]
    warned.update(name for name, _ in problems)
    if fresh:
        more = f" (and {len(fresh) - 3} more files)" if len(fresh) > 3 else ""
        warnings.warn(f"ground truth unknown for {len(fresh)} frame(s), whose pose file is not a pose; their "
                      f"images are still used: {'; '.join(fresh[:3])}{more}", DatasetWarning, stacklevel=4)
    return poses


class SevenScenesSequence(RGBDSequence):
    """A 7-Scenes sequence folder.

    Args:
        root: a folder holding ``frame-XXXXXX.color.*`` files (e.g. ``redkitchen/seq-01``).
        K: ``(3, 3)`` intrinsics overriding ``camera-intrinsics.txt`` / the default (the depth camera's; a
            registered camera's when the run has no rig).
        depth_scale: depth units per metre (default 1000, millimetres).
        fps: frame rate giving the timestamps ``k / fps``: a finite number > 0.

    Raises:
        DatasetNotFoundError: the folder does not exist.
        DatasetError: ``fps`` is not a finite positive number (a bool is refused too), no colour frames, a
            malformed ``camera-intrinsics.txt``, or depth whose median is not a camera's at ``depth_scale``
            (:func:`~slam.io.sequence.check_depth_units`).

    Example:
        >>> seq = SevenScenesSequence("7scenes-redkitchen")  # doctest: +SKIP
        >>> len(seq), seq[0].depth.shape  # doctest: +SKIP
        (1000, (480, 640))
    """

    depth_scale = SEVENSCENES_DEPTH_SCALE

    def __init__(self, root, K=None, fps: float = SEVENSCENES_FPS, depth_scale: float | None = None,
                 check_units: bool = True):
        self.root = Path(root).expanduser()
        if isinstance(fps, bool) or not isinstance(fps, Real) or not math.isfinite(fps) or not fps > 0:
            raise DatasetError(self.root, f"fps must be a finite positive number, got {fps!r}")
        if depth_scale is not None:
            self.depth_scale = check_depth_scale(depth_scale, self.root)
        if not self.root.is_dir():
            raise DatasetNotFoundError(self.root, "sequence folder does not exist")
        self.name = self.root.resolve().name
        found: dict[int, tuple[int, str, str]] = {}
        names = set(os.listdir(self.root))
        for fname in names:
            m = _COLOR_RE.match(fname)
            if m is None:
                continue
            number, digits = int(m.group(1)), m.group(1)
            rank = _PREFERENCE[m.group(2).lower()]
            if number not in found or rank < found[number][0]:
                found[number] = (rank, digits, fname)
        if not found:
            raise DatasetError(self.root, "no 7-Scenes colour frames (frame-000000.color.png|jpg) in this folder")
        numbers = sorted(found)
        self.frame_numbers = np.asarray(numbers, dtype=np.int64)
        self._color: list[str] = [found[k][2] for k in numbers]
        self._depth: list[str] = [f"frame-{found[k][1]}.depth.png" for k in numbers]
        pose_names = [f"frame-{found[k][1]}.pose.txt" for k in numbers]
        self._pose: list[str | None] = [p if p in names else None for p in pose_names]
        with np.errstate(over="ignore"):
            self._timestamps = self.frame_numbers.astype(np.float64) / float(fps)
        if not np.isfinite(self._timestamps).all():  # a subnormal fps
            raise DatasetError(self.root, f"fps={fps!r} is too small: frame {numbers[-1]} would be at "
                                          f"{self._timestamps[-1]} s")
        self._gt: np.ndarray | None = None
        self._warned: set[str] = set()  # pose files already reported as not a pose (each is warned once)

        if K is not None:
            self.K = check_intrinsics(K, "K")
        elif "camera-intrinsics.txt" in names:
            path = self.root / "camera-intrinsics.txt"
            try:
                self.K = check_intrinsics(_read_matrix(path, (3, 3)), str(path))
            except ValueError as e:
                raise DatasetError(path, str(e).removeprefix(f"{path} ")) from None
        else:
            self.K = SEVENSCENES_K.copy()
        if check_units:
            check_depth_units(self.root, [self.root / name for name in self._depth[:10]], self.depth_scale,
                              SEVENSCENES_INVALID_DEPTH)

    def paths(self, i: int) -> tuple[Path, Path]:
        """The colour and depth files of frame ``i``."""
        return self.root / self._color[i], self.root / self._depth[i]

    def _pose_of(self, i: int) -> np.ndarray:
        """``(7,)`` ground truth of frame ``i``, NaN if it has none (a file that is not a pose: with a warning)."""
        return _read_poses(self.root, [self._pose[i]], self._warned)[0]

    def _groundtruth_array(self) -> np.ndarray:
        if self._gt is None:  # read once, on first use
            self._gt = _read_poses(self.root, self._pose, self._warned)
        return self._gt

    def _load(self, i: int) -> RGBDFrame:
        rgb_path, depth_path = self.paths(i)
        rgb = read_rgb(str(rgb_path))
        raw = read_depth_raw(str(depth_path), rgb.shape[:2])
        # a pose file that is not a pose leaves the frame without ground truth (warned), never without images
        pose = self._gt[i] if self._gt is not None else self._pose_of(i)
        depth = depth_to_metres(raw, self.depth_scale, SEVENSCENES_INVALID_DEPTH)
        return self._frame(i, rgb, depth, pose, (rgb_path, depth_path))
