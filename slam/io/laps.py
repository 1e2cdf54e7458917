"""A sequence played as laps, forward, backward, forward, ... (docs/pipeline.md, "Long runs"): the motion stays
continuous (a turn shows its frame twice) and timestamps keep increasing by the source's spacing (its median at a
turn), so a time window spans the same time on every lap. Ground truth is the source frame's.

Example:
    >>> import numpy as np
    >>> from slam.synthetic import SyntheticSequence
    >>> seq = SyntheticSequence("loop", num_frames=4, width=32, height=24)
    >>> laps = LapSequence(seq, 3)
    >>> len(laps), laps.source_indices.tolist()
    (12, [0, 1, 2, 3, 3, 2, 1, 0, 0, 1, 2, 3])
    >>> bool(np.all(np.diff(laps.timestamps) > 0))
    True
"""
from __future__ import annotations

import numpy as np

from slam.io.frame import RGBDFrame
from slam.io.sequence import RGBDSequence

__all__ = ["LapSequence", "lap_indices"]


def lap_indices(num_frames: int, laps: int) -> np.ndarray:
    """``(laps * num_frames,)`` int64 source frame of each frame of ``laps`` alternating laps."""
    if isinstance(num_frames, bool) or not isinstance(num_frames, (int, np.integer)) or num_frames < 1:
        raise ValueError(f"a sequence played as laps needs at least one frame, got {num_frames!r}")
    if isinstance(laps, bool) or not isinstance(laps, (int, np.integer)) or laps < 1:
        raise ValueError(f"laps must be an integer >= 1, got {laps!r}")
    forward = np.arange(int(num_frames), dtype=np.int64)
    return np.concatenate([forward if k % 2 == 0 else forward[::-1] for k in range(int(laps))])


class LapSequence(RGBDSequence):
    """``source`` played ``laps`` times, alternately forward and backward.

    Args:
        source: any :class:`~slam.io.sequence.RGBDSequence` (a folder's, a view of one, a generated one).
        laps: the number of laps (1: the source itself, re-stamped from its first timestamp).

    Attributes:
        source_indices: ``(len,)`` int64 the source frame each frame shows.
    """

    def __init__(self, source: RGBDSequence, laps: int):
        if not isinstance(source, RGBDSequence):
            raise TypeError(f"LapSequence plays an RGBDSequence, got {type(source).__name__}")
        self.source, self.laps = source, int(laps) if not isinstance(laps, bool) else laps
        self.source_indices = lap_indices(len(source), laps)
        self.root, self.name, self.K = source.root, source.name, source.K
        src = np.asarray(source.timestamps, dtype=np.float64)
        step = np.diff(src)
        if step.size and not np.all(step > 0):
            bad = int(np.flatnonzero(~(step > 0))[0]) + 1
            raise ValueError(f"{source.name}: timestamps must increase to be played as laps (frame {bad}: "
                             f"{src[bad]!r} after {src[bad - 1]!r})")
        turn = float(np.median(step)) if step.size else 1.0 / 30.0
        idx = self.source_indices
        gaps = np.abs(src[idx[1:]] - src[idx[:-1]])
        gaps[idx[1:] == idx[:-1]] = turn  # the frame of a turn, shown again one spacing later
        self._timestamps = src[idx[0]] + np.concatenate([[0.0], np.cumsum(gaps)])
        self._gt = None

    def _load(self, i: int) -> RGBDFrame:
        frame = self.source[int(self.source_indices[i])]
        frame.index, frame.timestamp = int(i), float(self._timestamps[i])
        return frame

    def _groundtruth_array(self) -> np.ndarray:
        if self._gt is None:
            self._gt = np.asarray(self.source._groundtruth_array(), dtype=np.float64)[self.source_indices]
        return self._gt

    def __repr__(self) -> str:
        return f"LapSequence({self.source!r}, laps={self.laps})"
