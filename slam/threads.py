"""The thread counts a run computes with: torch's intra-op pool, the BLAS libraries' and OpenCV's.

Most of the pipeline's work is many small operations on one frame (the depth warp, ORB matching, RANSAC
hypotheses, a pose graph of a hundred keyframes). On a machine where another process keeps a core busy,
a pool with more threads than free cores waits at every operation's barrier for its descheduled thread:
the README's kitchen command on 60 frames took 41.7 s with torch's default threads and 4.5 s with one
(the depth warp went from 15 to 445 ms a frame). One thread loses little on an idle machine, because the
only large operation, the descriptor's CNN, runs once per keyframe (benchmarks/threads.py, figures in
docs/results.md "Threads"). So a run takes ``SLAMConfig.threads = 1`` by default.

:func:`limit_threads` sets the counts for a block and restores the caller's afterwards: a library must not
change its caller's process state for good. :func:`slam.pipeline.run_slam` applies it around the whole
run; :class:`slam.system.RGBDSLAM` applies it in each ``track`` / ``finish`` call (:func:`config_threads`;
~0.5 ms a call when the counts differ, nothing when they are already set), so a program driving it frame
by frame gets the configured count without doing anything, or wraps its own loop in one limit.

torch's inter-op pool is left alone (it can only be sized before its first use, and the pipeline does
not use it). BLAS goes through ``threadpoolctl`` (``attnloop[accel]``): without it BLAS keeps its own
count (:func:`slam.graph.blas_threads.blas_thread_control` says which).

Example:
    >>> import torch
    >>> before = torch.get_num_threads()
    >>> with limit_threads(1):
    ...     torch.get_num_threads()
    1
    >>> torch.get_num_threads() == before
    True
"""
from __future__ import annotations

import contextlib
import functools
import numbers
import threading
from collections.abc import Callable, Iterator

import cv2
import torch

__all__ = ["check_threads", "config_threads", "limit_threads", "thread_counts"]

# the count the innermost limit_threads of each thread set (None outside any)
_active = threading.local()


def check_threads(n: int | None, what: str = "threads") -> int | None:
    """``n`` as an int >= 1, or None (leave the counts as they are).

    Raises:
        ValueError: anything else (a bool, a float, 0, a negative number), naming ``what``.
    """
    if n is None:
        return None
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 1:
        raise ValueError(f"{what} must be a whole number >= 1 or None, got {n!r}")
    return int(n)


def thread_counts() -> dict:
    """The current counts: ``{"torch": int, "opencv": int, "blas": [int, ...]}`` (BLAS: one per library
    threadpoolctl finds, empty without it)."""
    from slam.graph.blas_threads import _blas_libraries

    return {"torch": torch.get_num_threads(), "opencv": cv2.getNumThreads(),
            "blas": [lib.get_num_threads() for lib in _blas_libraries()]}


@contextlib.contextmanager
def limit_threads(n: int | None) -> Iterator[None]:
    """torch, BLAS and OpenCV compute with ``n`` threads inside the block; the previous counts after.

    Inside a block of the same thread limited to the same ``n`` (and torch still at ``n``), it does nothing:
    a count changed by hand inside the outer block (OpenCV's, BLAS') is then left as it is.

    Args:
        n: the thread count (>= 1), or None to change nothing.

    Raises:
        ValueError: ``n`` is not None or a whole number >= 1.
    """
    n = check_threads(n)
    if n is None:
        yield
        return
    if getattr(_active, "count", None) == n and torch.get_num_threads() == n:
        # nested in a limit to the same count in this thread (RGBDSLAM.track inside run_slam): the counts
        # are set. No query of OpenCV's: cv2.getNumThreads releases the GIL, and taking it back while the
        # frame reader's threads run cost ~1 ms a call, two calls a frame
        yield
        return
    from slam.graph.blas_threads import limit_blas_threads  # (slam.graph imports this module's users)

    prev_torch, prev_cv = torch.get_num_threads(), cv2.getNumThreads()
    prev_active = getattr(_active, "count", None)
    if prev_torch != n:  # nested in a limit to the same count (track() inside run_slam): nothing to do
        torch.set_num_threads(n)
    if prev_cv != n:
        cv2.setNumThreads(n)
    try:
        _active.count = n
        with limit_blas_threads(n):
            yield
    finally:
        _active.count = prev_active
        if cv2.getNumThreads() != prev_cv:
            cv2.setNumThreads(prev_cv)
        if torch.get_num_threads() != prev_torch:
            torch.set_num_threads(prev_torch)


def config_threads(method: Callable) -> Callable:
    """Decorator of a method of an object with a ``config`` (:class:`slam.config.SLAMConfig`): the method
    runs under ``limit_threads(self.config.threads)``, so the streaming API (``RGBDSLAM.track`` /
    ``finish``) computes with the configured threads and gives the caller's back after each call."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        with limit_threads(getattr(self.config, "threads", None)):
            return method(self, *args, **kwargs)

    return wrapper
