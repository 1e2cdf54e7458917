"""TUM-format trajectories: ``timestamp tx ty tz qx qy qz qw`` per line, read strictly (every error names the file
and the 1-based line) and written with the shortest decimals that read back to the same float64.

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
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import IO, Optional, Union

import numpy as np
import torch

from slam.input_checks import MAX_COORDINATE, TextDecodeError, read_text_lines, source_name, unit_quaternions

__all__ = ["Trajectory", "TrajectoryFormatError", "read_tum_trajectory", "write_tum_trajectory"]

PathOrFile = Union[str, "os.PathLike[str]", IO[str]]


@dataclass
class Trajectory:
    """A timed sequence of camera-to-world poses.

    Attributes:
        timestamps: ``(N,)`` float64 seconds. An integer tensor is converted; a float32 or float16 one is
            refused with a ``TypeError`` (at Unix times float32 steps by 128 s).
        poses: ``(N, 7)`` float64 ``[tx, ty, tz, qx, qy, qz, qw]`` (other float or integer dtypes are
            converted to float64).
    """

    timestamps: torch.Tensor
    poses: torch.Tensor

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    def __post_init__(self) -> None:
        if not isinstance(self.timestamps, torch.Tensor) or not isinstance(self.poses, torch.Tensor):
            raise TypeError("Trajectory.timestamps and Trajectory.poses must be torch tensors")
        ts = self.timestamps
        if ts.is_floating_point() and ts.dtype != torch.float64:
            step = float(torch.finfo(ts.dtype).eps) * 2.0 ** 30
            raise TypeError(f"Trajectory.timestamps must be float64, got {ts.dtype}: it steps by {step:g} s at Unix "
                            f"times (~1e9 s), so such stamps have collapsed; build them with dtype=torch.float64")
        if ts.is_complex() or ts.dtype == torch.bool:
            raise TypeError(f"Trajectory.timestamps must be float64 seconds, got {ts.dtype}")
        self.timestamps = ts.to(torch.float64)  # integers converted (a float64 tensor is kept as it is)
        if self.poses.is_complex() or self.poses.dtype == torch.bool:
            raise TypeError(f"Trajectory.poses must be float64, got {self.poses.dtype}")
        self.poses = self.poses.to(torch.float64)
        if self.timestamps.dim() != 1:
            raise ValueError(f"timestamps must have shape (N,), got {tuple(self.timestamps.shape)}")
        if self.poses.shape != (self.timestamps.shape[0], 7):
            raise ValueError(
                f"poses must have shape (N, 7) with N = {self.timestamps.shape[0]} timestamps, "
                f"got {tuple(self.poses.shape)}"
            )

    @staticmethod
    def empty() -> Trajectory:
        """A trajectory with no poses: timestamps ``(0,)``, poses ``(0, 7)``."""
        return Trajectory(torch.zeros(0, dtype=torch.float64), torch.zeros(0, 7, dtype=torch.float64))

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
        line_number: 1-based line number of the offending line (None when a file object's decoder failed).
    """

    def __init__(self, path: str, line_number: Optional[int], message: str):
        self.path = path
        self.line_number = line_number
        where = f"{path}:{line_number}" if line_number is not None else path
        super().__init__(f"{where}: {message}")


def split_fields(line: str) -> tuple[list[str], int | None]:
    """The fields of a line separated by whitespace and/or commas, and the 1-based number of the first
    empty comma-separated cell (``"1,,2"``, a leading or a trailing comma), or None.

    Example:
        >>> split_fields("1, 2\t3 4"), split_fields("1,,2")
        ((['1', '2', '3', '4'], None), (['1', '2'], 2))
    """
    if "," not in line:
        return line.split(), None
    cells = line.split(",")
    empty = next((k + 1 for k, cell in enumerate(cells) if not cell.strip()), None)
    return [f for cell in cells for f in cell.split()], empty


def data_lines(lines: list[str], error: Callable[[int, str], Exception]) -> Iterator[tuple[int, str, list[str]]]:
    """``(line number, stripped line, fields)`` of each data line: ``#`` comments, blank lines and an uncommented
    ``timestamp ...`` header before the data are skipped; an empty comma-separated cell raises
    ``error(line number, message)``."""
    first = True
    for number, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields, empty = split_fields(line)
        if first and fields and fields[0].lower() == "timestamp":
            continue  # an uncommented column header before the data
        if empty is not None:
            raise error(number, f"comma-separated cell {empty} is empty in {line!r}")
        first = False
        yield number, line, fields


def _read_lines(source: PathOrFile) -> list[str]:
    if isinstance(source, (str, os.PathLike)) and not os.path.isfile(os.fspath(source)):
        if os.path.isdir(os.fspath(source)):
            raise IsADirectoryError(f"{os.fspath(source)}: a folder, not a trajectory file")
        raise FileNotFoundError(f"trajectory file not found: {os.fspath(source)}")
    if not isinstance(source, (str, os.PathLike)) and not hasattr(source, "read"):
        raise TypeError(f"expected a path or a text file object, got {type(source).__name__}")
    try:
        return read_text_lines(source)[1]
    except TextDecodeError as e:
        raise TrajectoryFormatError(e.path, e.line, e.reason) from None


def read_tum_trajectory(source: PathOrFile) -> Trajectory:
    """Read a TUM trajectory file.

    Lines starting with ``#``, blank lines, and a column-header line starting with the word ``timestamp``
    before the first pose are skipped. Quaternions are normalised. The result is sorted by timestamp (a
    stable sort); of lines sharing one timestamp the last is kept, as TUM's scripts do, with a warning.

    Args:
        source: a path or a file object (text, or binary: then decoded as UTF-8).

    Returns:
        a :class:`Trajectory` with timestamps ``(N,)`` and poses ``(N, 7)`` in float64; ``N = 0`` for
        a file without data lines.

    Raises:
        FileNotFoundError: the path does not exist.
        TrajectoryFormatError: a line is malformed (message ``file:line: reason``).
        TypeError: ``source`` is neither a path nor a text file object.
    """
    name = source_name(source)
    rows: list[list[float]] = []
    line_numbers: list[int] = []
    for number, line, fields in data_lines(_read_lines(source), lambda n, m: TrajectoryFormatError(name, n, m)):
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
        if max(abs(v) for v in values[1:4]) > MAX_COORDINATE:
            raise TrajectoryFormatError(name, number, f"translation beyond {MAX_COORDINATE:.0e} m (not a position) "
                                                      f"in {line!r}")
        rows.append(values)
        line_numbers.append(number)
    if not rows:
        return Trajectory.empty()

    data = np.asarray(rows, dtype=np.float64)
    unit, zero = unit_quaternions(data[:, 4:])
    if zero.any():
        k = int(np.nonzero(zero)[0][0])
        raise TrajectoryFormatError(name, line_numbers[k], f"zero quaternion {data[k, 4:].tolist()}; expected "
                                                            "qx qy qz qw of a rotation")
    data[:, 4:] = unit
    order = np.argsort(data[:, 0], kind="stable")
    data, lines = data[order], np.asarray(line_numbers)[order]
    same = np.flatnonzero(np.diff(data[:, 0]) == 0.0)
    if same.size:  # a run of equal stamps keeps its last member (the stable sort kept file order)
        keep = np.ones(len(data), dtype=bool)
        keep[same] = False
        warnings.warn(f"{name}: {same.size} duplicate timestamp(s) (e.g. line {int(lines[same[0] + 1])}); "
                      "kept the last pose of each", stacklevel=2)
        data = data[keep]
    poses = torch.from_numpy(data[:, 1:].copy())
    return Trajectory(torch.from_numpy(data[:, 0].copy()), poses)


def write_tum_trajectory(target: PathOrFile, traj: Trajectory, header: bool = True) -> None:
    """Write a trajectory in TUM format, one ``timestamp tx ty tz qx qy qz qw`` line per pose.

    Args:
        target: a path (parent folders must exist) or a text file object.
        traj: timestamps ``(N,)`` and poses ``(N, 7)``; written in the given order.
        header: write a ``# timestamp tx ty tz qx qy qz qw`` comment line first.
    """
    if not isinstance(traj, Trajectory):
        raise TypeError(f"expected a Trajectory, got {type(traj).__name__}")
    stamps = traj.timestamps.detach().to("cpu", torch.float64).numpy()
    poses = traj.poses.detach().to("cpu", torch.float64).numpy()
    if not (np.isfinite(stamps).all() and np.isfinite(poses).all()):
        raise ValueError("cannot write a trajectory with non-finite timestamps or poses")
    lines = ["# timestamp tx ty tz qx qy qz qw"] if header else []
    lines += [" ".join(map(repr, [t, *p])) for t, p in zip(stamps.tolist(), poses.tolist())]
    text = "\n".join(lines) + ("\n" if lines else "")
    if isinstance(target, (str, os.PathLike)):
        with open(os.fspath(target), "w", encoding="utf-8") as f:
            f.write(text)
    elif hasattr(target, "write"):
        target.write(text)
    else:
        raise TypeError(f"expected a path or a text file object, got {type(target).__name__}")
