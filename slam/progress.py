"""A dependency-free progress bar for long runs (writes to stderr, silent when not a TTY unless forced)."""
from __future__ import annotations

import sys
import time
from typing import Iterable, Iterator, Optional, TextIO, TypeVar

T = TypeVar("T")


class Progress:
    """Wrap an iterable and print ``desc  42% |#####     | 420/1000 [12.3 fps, eta 47s]``.

    Args:
        iterable: what to iterate over.
        total: number of items (defaults to ``len(iterable)`` when available).
        desc: a short label.
        stream: where to write (stderr by default).
        enabled: ``None`` = only when ``stream`` is a terminal; True/False force it.
        min_interval: seconds between redraws (keeps the overhead negligible).

    Example:
        >>> sum(Progress(range(3), enabled=False))
        3
    """

    def __init__(self, iterable: Iterable[T], total: Optional[int] = None, desc: str = "",
                 stream: Optional[TextIO] = None, enabled: Optional[bool] = None,
                 min_interval: float = 0.2, width: int = 30):
        self.iterable = iterable
        self.total = total if total is not None else (len(iterable) if hasattr(iterable, "__len__") else None)
        self.desc = desc
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = (self.stream.isatty() if hasattr(self.stream, "isatty") else False) \
            if enabled is None else enabled
        self.min_interval = min_interval
        self.width = width
        self.postfix = ""
        self.count = 0
        self._start = 0.0
        self._last = 0.0

    def set_postfix(self, text: str) -> None:
        """Extra text shown after the rate (e.g. ``loops=3``)."""
        self.postfix = text

    def _draw(self, final: bool = False) -> None:
        elapsed = max(time.perf_counter() - self._start, 1e-9)
        rate = self.count / elapsed
        if self.total:
            frac = min(self.count / self.total, 1.0)
            filled = int(round(frac * self.width))
            eta = (self.total - self.count) / rate if rate > 0 else 0.0
            line = (f"\r{self.desc} {frac * 100:5.1f}% |{'#' * filled}{' ' * (self.width - filled)}| "
                    f"{self.count}/{self.total} [{rate:.1f} it/s, eta {eta:.0f}s]")
        else:
            line = f"\r{self.desc} {self.count} [{rate:.1f} it/s]"
        if self.postfix:
            line += " " + self.postfix
        self.stream.write(line + ("\n" if final else ""))
        self.stream.flush()

    def __iter__(self) -> Iterator[T]:
        self._start = self._last = time.perf_counter()
        for item in self.iterable:
            yield item
            self.count += 1
            now = time.perf_counter()
            if self.enabled and now - self._last >= self.min_interval:
                self._last = now
                self._draw()
        if self.enabled:
            self._draw(final=True)
