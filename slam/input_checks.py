"""Checks every reader of files from the wild shares: UTF-8 text (:func:`read_text_lines`, an error naming the
file, line and byte), sane coordinates (:data:`MAX_COORDINATE`), the unit of timestamps (:func:`timestamp_unit`)
and quaternion normalisation that neither overflows nor underflows (:func:`unit_quaternions`).

Example:
    >>> import io
    >>> read_text_lines(io.BytesIO(b"a 1\\r\\nb 2\\n"))
    ('<stream>', ['a 1', 'b 2'])
    >>> try:
    ...     read_text_lines(io.BytesIO(b"ok\\nbad \\xff\\n"))
    ... except TextDecodeError as e:
    ...     print(e.line, e.reason)
    2 byte 0xff at column 5 is not UTF-8 text
    >>> q, zero = unit_quaternions(np.array([[1e200, 1e200, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]))
    >>> q[0].round(6).tolist(), zero.tolist()
    ([0.707107, 0.707107, 0.0, 0.0], [False, True])
"""
from __future__ import annotations

import os
import re
from typing import IO, List, Optional, Tuple, Union

import numpy as np

__all__ = ["MAX_COORDINATE", "TIME_UNITS", "PathOrFile", "TextDecodeError", "read_text_lines", "source_name",
           "timestamp_unit", "unit_quaternions"]

PathOrFile = Union[str, "os.PathLike[str]", IO[str], IO[bytes]]

_NEWLINE = re.compile(r"\r\n|\r|\n")

MAX_COORDINATE = 1e9  # metres: larger than any map, small enough that squares of positions stay far from overflow
# a quaternion shorter than this is "zero" (TUM files print 4 decimals: real ones have norm ~1)
_MIN_QUATERNION_NORM = 1e-6


class TextDecodeError(ValueError):
    """A file that is not UTF-8 text.

    Attributes:
        path: the file name (``"<stream>"`` for an unnamed file object).
        line: 1-based line of the first bad byte, or None when it cannot be known (a text-mode file object
            whose decoder failed).
        reason: what is wrong, without the location.
    """

    def __init__(self, path: str, line: Optional[int], reason: str):
        self.path, self.line, self.reason = path, line, reason
        where = f"{path}:{line}" if line is not None else path
        super().__init__(f"{where}: {reason}")


def source_name(source) -> str:
    """The name of a path or file object, as the error messages print it."""
    if isinstance(source, (str, os.PathLike)):
        return os.fspath(source)
    return str(getattr(source, "name", "<stream>"))


def _decode(data: bytes, name: str) -> str:
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        start = e.start
        line = data.count(b"\n", 0, start) + 1
        column = start - (data.rfind(b"\n", 0, start) + 1) + 1
        raise TextDecodeError(name, line, f"byte 0x{data[start]:02x} at column {column} is not UTF-8 text") from None


def read_text_lines(source: PathOrFile) -> Tuple[str, List[str]]:
    """The lines of a UTF-8 text file, without their line endings.

    Args:
        source: a path, or a file object opened in binary mode (checked here) or text mode (decoded by the
            file object; its failure is reported without a line number).

    Returns:
        ``(name, lines)``: the name errors should print and the list of lines (a final newline does not
        add an empty line).

    Raises:
        FileNotFoundError: the path does not exist; IsADirectoryError / PermissionError as ``open``.
        TextDecodeError: a byte that is not UTF-8, with the file, line and byte.
        TypeError: ``source`` is neither a path nor a file object.
    """
    name = source_name(source)
    if isinstance(source, (str, os.PathLike)):
        with open(os.fspath(source), "rb") as f:
            text = _decode(f.read(), name)
    elif hasattr(source, "read"):
        try:
            data = source.read()
        except UnicodeDecodeError as e:
            raise TextDecodeError(name, None, f"not UTF-8 text ({e.reason}, byte 0x{e.object[e.start]:02x}); "
                                              "open the file with encoding='utf-8'") from None
        text = _decode(data, name) if isinstance(data, (bytes, bytearray)) else data
        if not isinstance(text, str):
            raise TypeError(f"{name}: read() returned {type(data).__name__}, expected str or bytes")
        text = text.removeprefix("\ufeff")
    else:
        raise TypeError(f"expected a path or a file object, got {type(source).__name__}")
    lines = _NEWLINE.split(text)
    if lines and lines[-1] == "":
        lines.pop()
    return name, lines


def unit_quaternions(q: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Unit quaternions ``(N, 4)`` from finite quaternions ``q (N, 4)``, and which of them are zero.

    The norm is computed on ``q / max|q_k|`` (no overflow nor underflow); a quaternion with norm below ``1e-6``
    is reported as zero (its row of the result is then meaningless). The sign is kept.

    Returns:
        ``(unit (N, 4) float64, zero (N,) bool)``.
    """
    q = np.asarray(q, dtype=np.float64)
    scale = np.abs(q).max(axis=-1, keepdims=True)
    safe = np.where(scale > 0, scale, 1.0)
    r = q / safe
    n = np.sqrt((r * r).sum(axis=-1, keepdims=True))
    zero = (scale[..., 0] * n[..., 0] < _MIN_QUATERNION_NORM) | (scale[..., 0] == 0)
    return r / np.where(n > 0, n, 1.0), zero


#: Units of time by name, in units per second.
TIME_UNITS = {"seconds": 1.0, "milliseconds": 1e3, "microseconds": 1e6, "nanoseconds": 1e9}
# (unit, the smallest median spacing read as that unit): the boundaries split camera rates, 0.1-100 Hz, without overlap
_STAMP_UNITS = (("nanoseconds", 1e7), ("microseconds", 1e4), ("milliseconds", 10.0))


def timestamp_unit(stamps) -> Tuple[str, Optional[float], float]:
    """The unit of timestamps, from the median spacing of the distinct ones.

    Args:
        stamps: ``(N,)`` timestamps, in any order.

    Returns:
        ``(unit, units_per_second, spacing)``: ``("seconds", 1.0, d)``, ``("milliseconds", 1e3, d)``,
        ``("microseconds", 1e6, d)``, ``("nanoseconds", 1e9, d)``, or ``("frame numbers", None, 1.0)`` for
        whole numbers one apart (no time at all); ``d`` is the median spacing in the unit found (0 for fewer
        than two distinct stamps, read as seconds).

    Example:
        >>> timestamp_unit([1.7e18, 1.7e18 + 33_333_333, 1.7e18 + 66_666_667])[:2]
        ('nanoseconds', 1000000000.0)
        >>> timestamp_unit([0.0, 0.033, 0.067])[:2], timestamp_unit([0, 1, 2, 3])[:2]
        (('seconds', 1.0), ('frame numbers', None))
    """
    t = np.unique(np.asarray(stamps, dtype=np.float64))
    if t.size < 2:
        return "seconds", 1.0, 0.0
    d = float(np.median(np.diff(t)))
    if d == 1.0 and bool(np.all(t == np.round(t))):
        return "frame numbers", None, d
    for unit, least in _STAMP_UNITS:
        if d >= least:
            return unit, TIME_UNITS[unit], d
    return "seconds", 1.0, d
