"""The common RGB-D sequence interface (:func:`slam.io.open_sequence` opens a folder as one) and its errors.

Open-time errors are :class:`DatasetError` (a ``ValueError``; :class:`DatasetNotFoundError` also a
``FileNotFoundError``) naming the file and line; read-time ones :class:`slam.io.images.FrameReadError`, which a run
skips with a warning. Depth is float32 metres, 0.0 marking invalid pixels (never NaN).
"""
from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch

from slam.input_checks import TextDecodeError, read_text_lines
from slam.io.frame import DEPTH_MEDIAN_RANGE, RGBDFrame, median_valid_depth
from slam.io.images import FrameReadError, depth_to_metres, read_depth_raw
from slam.io.trajectory import Trajectory

__all__ = ["DatasetError", "DatasetNotFoundError", "DatasetWarning", "RGBDSequence", "SequenceView",
           "check_depth_scale", "check_depth_units"]

logger = logging.getLogger(__name__)


class DatasetError(ValueError):
    """A dataset folder or list file that cannot be used (raised when the sequence is opened).

    Attributes:
        path: the folder or file concerned.
        line_number: 1-based line of a malformed list entry, or None.
    """

    def __init__(self, path, message: str, line_number: int | None = None):
        self.path = str(path)
        self.line_number = line_number
        where = f"{self.path}:{line_number}" if line_number is not None else self.path
        super().__init__(f"{where}: {message}")


class DatasetNotFoundError(DatasetError, FileNotFoundError):
    """The sequence folder or one of its required list files does not exist."""


def read_dataset_lines(path: Path) -> list[str]:
    """The lines of a dataset's text file; a byte that is not UTF-8 is a :class:`DatasetError` naming the line."""
    try:
        return read_text_lines(path)[1]
    except TextDecodeError as e:
        raise DatasetError(path, e.reason, e.line) from None


def check_depth_scale(depth_scale, root) -> float:
    """``depth_scale`` (depth units per metre) as a float, or a :class:`DatasetError` naming ``root``."""
    try:
        value = float(depth_scale)
    except (TypeError, ValueError):
        value = float("nan")
    if isinstance(depth_scale, bool) or not (value > 0 and value < float("inf")):
        raise DatasetError(root, f"depth_scale must be a positive number of depth units per metre (TUM 5000, "
                                 f"millimetres 1000), got {depth_scale!r}")
    return value


#: Depth units per metre of the common 16-bit depth images, and what they are.
KNOWN_DEPTH_SCALES = {1000.0: "millimetres", 5000.0: "TUM's 1/5000 m"}
# frames whose depth the check reads (the first readable ones among the first few)
_UNIT_CHECK_FRAMES, _UNIT_CHECK_TRIES = 3, 10
_TYPICAL_DEPTH = 2.0  # metres: an indoor RGB-D view's median depth, to order the scales an error suggests


def check_depth_units(root, depth_paths: Sequence, scale: float, invalid_values: tuple[int, ...] = (0,),
                      read: Callable[[object], np.ndarray] = read_depth_raw) -> None:
    """Refuse depth whose median over the first readable frames (up to 3 of the first 10) is outside
    :data:`~slam.io.frame.DEPTH_MEDIAN_RANGE` metres at ``scale`` (millimetres read as TUM's 1/5000 m, ...).

    Args:
        root: the sequence folder (named by the error).
        depth_paths: the depth images of the frames, in order (the first 10 are read at most).
        scale: the depth units per metre in use.
        invalid_values: raw values meaning "no measurement".
        read: ``depth_paths[k] -> (H, W)`` raw depth (default: the 16-bit PNG reader); raises FrameReadError.

    Raises:
        DatasetError: one line naming the median found, the scale in use, the likely one and ``--depth-scale``.
    """
    medians = []
    for path in depth_paths[:_UNIT_CHECK_TRIES]:
        try:
            depth = depth_to_metres(read(path), scale, invalid_values)
        except FrameReadError:
            continue
        med = median_valid_depth(depth)
        if med > 0:
            medians.append(med)
        if len(medians) == _UNIT_CHECK_FRAMES:
            break
    if not medians:
        return
    med = float(np.median(medians))
    lo, hi = DEPTH_MEDIAN_RANGE
    if lo <= med <= hi:
        return
    raw = med * scale
    fits = [c for c in KNOWN_DEPTH_SCALES if c != scale and lo <= raw / c <= hi]
    if fits:  # the likeliest first: nearest a room's typical 2 m
        fits.sort(key=lambda c: abs(np.log(raw / c / _TYPICAL_DEPTH)))
        fix = " or ".join(f"{KNOWN_DEPTH_SCALES[c]}? give --depth-scale {c:g} (depth_scale={c:g} in Python), which "
                          f"puts it at {raw / c:.3g} m" for c in fits)
    else:
        fix = f"give --depth-scale UNITS, the depth images' units per metre (median raw value {raw:g})"
    raise DatasetError(root, f"depth at {scale:g} units per metre has a median of {med:.3g} m in its first "
                             f"{len(medians)} frame(s), outside the {lo:g}-{hi:g} m of an RGB-D camera: {fix} "
                             "(--no-depth-check if the scene really is that near or far)")


def _known(pose: np.ndarray) -> np.ndarray | None:
    """A copy of ``pose (7,)`` float64, None where it holds a NaN (unknown)."""
    return None if np.isnan(pose).any() else np.array(pose, dtype=np.float64)


class DatasetWarning(UserWarning):
    """Something in a dataset was unusable and left out (e.g. a pose file that is not a pose); the message
    names the files."""


class RGBDSequence(ABC):
    """A lazily read RGB-D sequence: ``seq[i]`` decodes frame ``i`` (an :class:`RGBDFrame`), ``seq[a:b]`` is a
    :class:`SequenceView`; nothing but file names and timestamps is held in memory.

    Subclasses set ``root`` (Path), ``name`` (str), ``K`` ``(3, 3)`` float64 and ``_timestamps`` (or override
    ``__len__`` and ``timestamps``), and implement :meth:`_load` and :meth:`_groundtruth_array`.
    """

    root: Path
    name: str
    K: np.ndarray
    _timestamps: np.ndarray

    def __len__(self) -> int:
        return len(self._timestamps)

    @property
    def timestamps(self) -> np.ndarray:
        """``(N,)`` float64 seconds, one per frame, in input order."""
        return self._timestamps

    @abstractmethod
    def _load(self, i: int) -> RGBDFrame:
        """Decode frame ``i`` (``0 <= i < len``); raises FrameReadError."""

    @abstractmethod
    def _groundtruth_array(self) -> np.ndarray:
        """``(N, 7)`` float64 per-frame ground truth, NaN rows where unknown."""

    def __getitem__(self, i: int | slice):
        if isinstance(i, slice):
            return SequenceView(self, range(len(self))[i])
        if not isinstance(i, (int, np.integer)):
            raise TypeError(f"sequence indices must be integers or slices, got {type(i).__name__}")
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame index {i} out of range for a sequence of {n} frames")
        return self._load(int(i) % n)

    def __iter__(self) -> Iterator[RGBDFrame]:
        for i in range(len(self)):
            yield self[i]

    def frames(self, on_error: str = "raise", prefetch: int = 0,
               then: Callable[[RGBDFrame], object] | None = None) -> Iterator[RGBDFrame | FrameReadError]:
        """Iterate over the frames, optionally skipping unreadable ones and decoding ahead.

        Args:
            on_error: ``"raise"`` (re-raise :class:`FrameReadError`), ``"skip"`` (log a warning and
                go on with the next frame) or ``"yield"`` (yield the :class:`FrameReadError` in the
                frame's place, so a caller can keep one entry per input frame).
            prefetch: decode up to this many frames ahead in background threads; 0 reads in the caller.
            then: applied to each frame read, in the thread that read it (e.g. feature extraction); its
                result is yielded in the frame's place (a :class:`FrameReadError` as it is). An error it
                raises is raised here.
        """
        if on_error not in ("raise", "skip", "yield"):
            raise ValueError(f"on_error must be 'raise', 'skip' or 'yield', got {on_error!r}")
        n = len(self)
        if prefetch <= 0:
            for i in range(n):
                frame = self._try_load(i, on_error, then)
                if frame is not None:
                    yield frame
            return
        pool = ThreadPoolExecutor(max_workers=int(prefetch), thread_name_prefix="rgbd-prefetch")
        try:
            pending = deque(pool.submit(self._try_load, i, on_error, then) for i in range(min(n, prefetch + 1)))
            next_i = len(pending)
            while pending:
                frame = pending.popleft().result()
                if next_i < n:
                    pending.append(pool.submit(self._try_load, next_i, on_error, then))
                    next_i += 1
                if frame is not None:
                    yield frame
        finally:
            pool.shutdown(wait=True, cancel_futures=True)

    def _try_load(self, i: int, on_error: str, then=None):
        try:
            frame = self[i]
        except FrameReadError as e:
            if on_error == "raise":
                raise
            if on_error == "yield":
                return e
            logger.warning("skipping frame %d of %s: %s", i, self.name, e)
            return None
        return frame if then is None else then(frame)

    def _groundtruth_of(self, indices: np.ndarray) -> np.ndarray:
        """``(len(indices), 7)`` ground truth of a subset of the frames, as if they were the sequence (a reader
        associating by time associates again for the subset). Here: the frames' own rows."""
        return self._groundtruth_array()[indices]

    def groundtruth_pose(self, i: int) -> np.ndarray | None:
        """``(7,)`` ground truth of frame ``i`` or None."""
        return _known(self._groundtruth_array()[i])

    def _frame(self, i: int, rgb: np.ndarray, depth: np.ndarray, pose: np.ndarray, paths=("", "")) -> RGBDFrame:
        """Frame ``i`` of decoded images ``rgb (H, W, 3)``, ``depth (H, W)`` metres and ground truth ``pose (7,)``
        (NaN: unknown); ``paths``: the colour and depth files."""
        return RGBDFrame(index=i, timestamp=float(self.timestamps[i]), rgb=rgb, depth=depth, K=self.K.copy(),
                         pose_gt=_known(pose), rgb_path=str(paths[0]), depth_path=str(paths[1]))

    @property
    def groundtruth(self) -> Trajectory | None:
        """Ground truth of the frames that have it (input order, the frames' stamps), or None if none has."""
        gt = self._groundtruth_array()
        has = ~np.isnan(gt).any(axis=1)
        if not has.any():
            return None
        return Trajectory(torch.from_numpy(self.timestamps[has].copy()), torch.from_numpy(gt[has].copy()))

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, frames={len(self)}, root={str(self.root)!r})"


class SequenceView(RGBDSequence):
    """A subset of another sequence's frames (``seq[a:b]``); frames are re-indexed from 0."""

    def __init__(self, parent: RGBDSequence, indices: Sequence[int]):
        self.parent = parent
        self.indices = np.asarray(list(indices), dtype=np.int64)
        self.root, self.name, self.K = parent.root, parent.name, parent.K

    def __len__(self) -> int:
        return int(self.indices.size)

    @property
    def timestamps(self) -> np.ndarray:
        return self.parent.timestamps[self.indices]

    def _load(self, i: int) -> RGBDFrame:
        frame = self.parent._load(int(self.indices[i]))
        frame.index = i
        frame.pose_gt = self.groundtruth_pose(i)
        return frame

    def _groundtruth_array(self) -> np.ndarray:
        if getattr(self, "_gt", None) is None:
            self._gt = self.parent._groundtruth_of(self.indices)
        return self._gt

    def _groundtruth_of(self, indices: np.ndarray) -> np.ndarray:
        return self.parent._groundtruth_of(self.indices[indices])
