"""TUM-format trajectories: ``timestamp tx ty tz qx qy qz qw`` per line.

The reader is strict: every non-comment line must hold exactly eight finite numbers (separated by
spaces, tabs or commas, as TUM's own scripts accept) and a non-zero quaternion; anything else raises
:class:`TrajectoryFormatError` naming the file and the 1-based line number.

Example:
    >>> import io, torch
    >>> traj = Trajectory(torch.tensor([0.0, 0.1], dtype=torch.float64),
    ...                   torch.tensor([[0.0, 0, 0, 0, 0, 0, 1], [1.0, 0, 0, 0, 0, 0, 1]], dtype=torch.float64))
    >>> buf = io.StringIO()
    >>> write_tum_trajectory(buf, traj)
    >>> _ = buf.seek(0)
    >>> read_tum_trajectory(buf).poses.shape
    torch.Size([2, 7])
"""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from typing import IO, Union

import numpy as np
import torch

__all__ = ["Trajectory", "TrajectoryFormatError", "read_tum_trajectory", "write_tum_trajectory"]

PathOrFile = Union[str, "os.PathLike[str]", IO[str]]


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

    def __post_init__(self) -> None:
        if not isinstance(self.timestamps, torch.Tensor) or not isinstance(self.poses, torch.Tensor):
            raise TypeError("Trajectory.timestamps and Trajectory.poses must be torch tensors")
        if self.timestamps.dim() != 1:
            raise ValueError(f"timestamps must have shape (N,), got {tuple(self.timestamps.shape)}")
        if self.poses.shape != (self.timestamps.shape[0], 7):
            raise ValueError(
                f"poses must have shape (N, 7) with N = {self.timestamps.shape[0]} timestamps, "
                f"got {tuple(self.poses.shape)}"
            )

    @staticmethod
    def empty(dtype: torch.dtype = torch.float64, device=None) -> Trajectory:
        """A trajectory with no poses: timestamps ``(0,)``, poses ``(0, 7)``."""
        return Trajectory(torch.zeros(0, dtype=dtype, device=device), torch.zeros(0, 7, dtype=dtype, device=device))

    def subset(self, index: torch.Tensor) -> Trajectory:
        """The poses selected by an index or boolean mask tensor, as a new trajectory."""
        return Trajectory(self.timestamps[index], self.poses[index])

    @property
    def positions(self) -> torch.Tensor:
        """``(N, 3)`` camera centres in the world frame."""
        return self.poses[:, :3]


class TrajectoryFormatError(ValueError):
    """A trajectory file line that is not ``timestamp tx ty tz qx qy qz qw``.

    Attributes:
        path: the file name (``"<stream>"`` for an unnamed file object).
        line_number: 1-based line number of the offending line.
    """

    def __init__(self, path: str, line_number: int, message: str):
        self.path = path
        self.line_number = line_number
        super().__init__(f"{path}:{line_number}: {message}")


def _name_of(source) -> str:
    if isinstance(source, (str, os.PathLike)):
        return os.fspath(source)
    return str(getattr(source, "name", "<stream>"))


def _read_lines(source: PathOrFile) -> list[str]:
    if isinstance(source, (str, os.PathLike)):
        path = os.fspath(source)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"trajectory file not found: {path}")
        with open(path, "r", encoding="utf-8") as f:
            return f.read().splitlines()
    if hasattr(source, "read"):
        text = source.read()
        if isinstance(text, bytes):
            raise TypeError(f"{_name_of(source)}: open the trajectory file in text mode ('r'), not binary")
        return text.splitlines()
    raise TypeError(f"expected a path or a text file object, got {type(source).__name__}")


def read_tum_trajectory(source: PathOrFile, on_duplicate: str = "last") -> Trajectory:
    """Read a TUM trajectory file.

    Lines starting with ``#``, blank lines, and a column-header line starting with the word
    ``timestamp`` before the first pose are skipped. Values may be separated by spaces, tabs or
    commas. Quaternions are normalised (TUM files print 4 decimals, so they are not exactly unit).
    The result is sorted by timestamp (a stable sort: unsorted files are accepted).

    Args:
        source: a path or a text file object.
        on_duplicate: what to do with lines sharing one timestamp: ``"last"`` keeps the last one (the
            behaviour of TUM's dictionary-based scripts), ``"first"`` keeps the first, ``"error"``
            raises :class:`TrajectoryFormatError`. Kept duplicates are reported with a warning.

    Returns:
        a :class:`Trajectory` with timestamps ``(N,)`` and poses ``(N, 7)`` in float64; ``N = 0`` for
        a file without data lines.

    Raises:
        FileNotFoundError: the path does not exist.
        TrajectoryFormatError: a line is malformed (message ``file:line: reason``).
        TypeError: ``source`` is neither a path nor a text file object.
    """
    if on_duplicate not in ("last", "first", "error"):
        raise ValueError(f"on_duplicate must be 'last', 'first' or 'error', got {on_duplicate!r}")
    name = _name_of(source)
    rows: list[list[float]] = []
    line_numbers: list[int] = []
    for number, raw in enumerate(_read_lines(source), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").replace("\t", " ").split()
        if not rows and fields[0].lower() == "timestamp":
            continue  # an uncommented column header before the data (some copies of TUM files have one)
        if len(fields) != 8:
            raise TrajectoryFormatError(
                name, number, f"expected 8 values 'timestamp tx ty tz qx qy qz qw', got {len(fields)}: {line!r}"
            )
        try:
            values = [float(v) for v in fields]
        except ValueError:
            raise TrajectoryFormatError(name, number, f"not a number in {line!r}") from None
        if not all(np.isfinite(values)):
            raise TrajectoryFormatError(name, number, f"non-finite value in {line!r}")
        if sum(v * v for v in values[4:]) < 1e-12:
            raise TrajectoryFormatError(name, number, f"zero quaternion in {line!r}")
        rows.append(values)
        line_numbers.append(number)
    if not rows:
        return Trajectory.empty()

    data = np.asarray(rows, dtype=np.float64)
    order = np.argsort(data[:, 0], kind="stable")
    data, lines = data[order], np.asarray(line_numbers)[order]
    same = np.flatnonzero(np.diff(data[:, 0]) == 0.0)
    if same.size:
        if on_duplicate == "error":
            raise TrajectoryFormatError(name, int(lines[same[0] + 1]), f"duplicate timestamp {data[same[0], 0]!r}")
        # A run of equal stamps keeps its first (or last) member; the stable sort kept file order.
        drop = same + 1 if on_duplicate == "first" else same
        keep = np.ones(len(data), dtype=bool)
        keep[drop] = False
        warnings.warn(
            f"{name}: {same.size} duplicate timestamp(s) (e.g. line {int(lines[same[0] + 1])}); "
            f"kept the {on_duplicate} pose of each",
            stacklevel=2,
        )
        data = data[keep]
    poses = torch.from_numpy(data[:, 1:].copy())
    poses[:, 3:] = poses[:, 3:] / poses[:, 3:].norm(dim=-1, keepdim=True)
    return Trajectory(torch.from_numpy(data[:, 0].copy()), poses)


def write_tum_trajectory(target: PathOrFile, traj: Trajectory, header: bool = True, precision: int = 9) -> None:
    """Write a trajectory in TUM format, one ``timestamp tx ty tz qx qy qz qw`` line per pose.

    Args:
        target: a path (parent folders must exist) or a text file object.
        traj: timestamps ``(N,)`` and poses ``(N, 7)``; written in the given order.
        header: write a ``# timestamp tx ty tz qx qy qz qw`` comment line first.
        precision: decimals of the pose values (timestamps always get 6, TUM's own precision).
    """
    if not isinstance(traj, Trajectory):
        raise TypeError(f"expected a Trajectory, got {type(traj).__name__}")
    stamps = traj.timestamps.detach().to("cpu", torch.float64).numpy()
    poses = traj.poses.detach().to("cpu", torch.float64).numpy()
    if not (np.isfinite(stamps).all() and np.isfinite(poses).all()):
        raise ValueError("cannot write a trajectory with non-finite timestamps or poses")
    fmt = "%.6f" + (" %." + str(int(precision)) + "f") * 7
    lines = ["# timestamp tx ty tz qx qy qz qw"] if header else []
    lines += [fmt % (t, *p) for t, p in zip(stamps.tolist(), poses.tolist())]
    text = "\n".join(lines) + ("\n" if lines else "")
    if isinstance(target, (str, os.PathLike)):
        with open(os.fspath(target), "w", encoding="utf-8") as f:
            f.write(text)
    elif hasattr(target, "write"):
        target.write(text)
    else:
        raise TypeError(f"expected a path or a text file object, got {type(target).__name__}")
