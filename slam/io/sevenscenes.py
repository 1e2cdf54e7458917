"""Microsoft 7-Scenes sequences (one ``seq-XX`` folder), read lazily.

Layout: ``frame-%06d.color.(png|jpg)``, ``frame-%06d.depth.png`` (16-bit millimetres, 0 and 65535
invalid), ``frame-%06d.pose.txt`` (4x4 camera-to-world, optional), optional ``camera-intrinsics.txt``
(3x3; default fx = fy = 585, cx = 320, cy = 240). Pose rotations are projected onto the nearest
rotation matrix (KinectFusion's are off by up to 5e-4). There are no timestamps: frame number ``k`` is at
``k / 30`` s. Colour and depth come from two unregistered cameras; they are treated as registered, as
is customary for this dataset.

Frames are found from the colour files at open time (one directory listing); images and poses are read
only when a frame is requested. A pose file with non-finite entries (7-Scenes marks lost tracking so)
means "no ground truth" for that frame.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import torch

from slam.io.frame import RGBDFrame
from slam.io.images import FrameReadError, depth_to_metres, read_depth_raw, read_rgb
from slam.io.sequence import DatasetError, DatasetNotFoundError, RGBDSequence
from slam.lie import se3_from_matrix

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


def _read_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    try:
        values = np.array(path.read_text().split(), dtype=np.float64)
    except ValueError:
        raise DatasetError(path, f"expected {shape[0]}x{shape[1]} numbers") from None
    if values.size != shape[0] * shape[1]:
        raise DatasetError(path, f"expected {shape[0] * shape[1]} numbers ({shape[0]}x{shape[1]}), got {values.size}")
    return values.reshape(shape)


def _matrices_to_poses(T: np.ndarray) -> np.ndarray:
    """``(N, 4, 4)`` camera-to-world matrices -> ``(N, 7)`` poses.

    The KinectFusion rotations are not exactly orthonormal (determinants 0.9995-0.9999 in redkitchen):
    they are replaced by the nearest rotation (polar decomposition, ``U V^T``) before conversion.
    """
    Tt = torch.from_numpy(np.ascontiguousarray(T, dtype=np.float64))
    U, _, Vh = torch.linalg.svd(Tt[:, :3, :3])
    d = torch.sign(torch.det(U @ Vh))
    R = U @ torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1)) @ Vh
    return se3_from_matrix(torch.cat([R, Tt[:, :3, 3:]], dim=-1)).numpy()


class SevenScenesSequence(RGBDSequence):
    """A 7-Scenes sequence folder.

    Args:
        root: a folder holding ``frame-XXXXXX.color.*`` files (e.g. ``redkitchen/seq-01``).
        K: ``(3, 3)`` intrinsics overriding ``camera-intrinsics.txt`` / the default.
        fps: frame rate giving the timestamps ``k / fps``.

    Raises:
        DatasetNotFoundError: the folder does not exist.
        DatasetError: no colour frames, or a malformed ``camera-intrinsics.txt``.

    Example:
        >>> seq = SevenScenesSequence("7scenes-redkitchen")  # doctest: +SKIP
        >>> len(seq), seq[0].depth.shape  # doctest: +SKIP
        (1000, (480, 640))
    """

    depth_scale = SEVENSCENES_DEPTH_SCALE

    def __init__(self, root, K=None, fps: float = SEVENSCENES_FPS):
        self.root = Path(root).expanduser()
        if not self.root.is_dir():
            raise DatasetNotFoundError(self.root, "sequence folder does not exist")
        self.name = self.root.resolve().name
        found: dict[int, tuple[int, str, str]] = {}
        with os.scandir(self.root) as it:
            names = {e.name for e in it}
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
        self._timestamps = self.frame_numbers.astype(np.float64) / float(fps)
        self._gt: np.ndarray | None = None

        if K is not None:
            K = np.asarray(K, dtype=np.float64)
            if K.shape != (3, 3):
                raise ValueError(f"K must have shape (3, 3), got {K.shape}")
            self.K = K.copy()
        elif "camera-intrinsics.txt" in names:
            self.K = _read_matrix(self.root / "camera-intrinsics.txt", (3, 3))
        else:
            self.K = SEVENSCENES_K.copy()

    def __len__(self) -> int:
        return len(self._color)

    @property
    def timestamps(self) -> np.ndarray:
        return self._timestamps

    def paths(self, i: int) -> tuple[Path, Path]:
        """The colour and depth files of frame ``i``."""
        return self.root / self._color[i], self.root / self._depth[i]

    def _pose_of(self, i: int) -> np.ndarray:
        """``(7,)`` ground truth of frame ``i``, NaN if it has none (no file, or non-finite entries)."""
        if self._pose[i] is None:
            return np.full(7, np.nan)
        T = _read_matrix(self.root / self._pose[i], (4, 4))
        if not np.isfinite(T).all():
            return np.full(7, np.nan)
        return _matrices_to_poses(T[None])[0]

    def _groundtruth_array(self) -> np.ndarray:
        if self._gt is None:  # read once, on first use (~0.1 ms per pose file)
            Ts = np.full((len(self), 4, 4), np.nan)
            for i, name in enumerate(self._pose):
                if name is not None:
                    Ts[i] = _read_matrix(self.root / name, (4, 4))
            ok = np.isfinite(Ts).all(axis=(1, 2))
            gt = np.full((len(self), 7), np.nan)
            if ok.any():
                gt[ok] = _matrices_to_poses(Ts[ok])
            self._gt = gt
        return self._gt

    def _load(self, i: int) -> RGBDFrame:
        rgb_path, depth_path = self.paths(i)
        rgb = read_rgb(str(rgb_path))
        raw = read_depth_raw(str(depth_path), rgb.shape[:2])
        if self._gt is not None:
            pose = self._gt[i]
        else:
            try:
                pose = self._pose_of(i)
            except DatasetError as e:  # a corrupt pose file is a per-frame read problem here
                raise FrameReadError(e.path, str(e)) from None
        return RGBDFrame(
            index=i, timestamp=float(self._timestamps[i]), rgb=rgb,
            depth=depth_to_metres(raw, self.depth_scale, SEVENSCENES_INVALID_DEPTH), K=self.K.copy(),
            pose_gt=None if np.isnan(pose).any() else np.array(pose, dtype=np.float64),
            rgb_path=str(rgb_path), depth_path=str(depth_path),
        )
