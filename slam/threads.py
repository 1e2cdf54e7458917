"""The thread counts a run computes with: torch's intra-op pool, the BLAS and OpenMP libraries' and OpenCV's.

Most of the pipeline's work is many small operations on one frame (the depth warp, ORB matching, RANSAC
hypotheses, a pose graph of a hundred keyframes). On a machine where another process keeps a core busy,
a pool with more threads than free cores waits at every operation's barrier for its descheduled thread:
the README's kitchen command on 60 frames took 41.7 s with torch's default threads and 4.5 s with one
(the depth warp went from 15 to 445 ms a frame). One thread loses little on an idle machine, because the
only large operation, the descriptor's CNN, runs once per keyframe (benchmarks/threads.py, figures in
docs/results.md "Threads"). So a run takes ``SLAMConfig.threads = 1`` by default.

:func:`limit_threads` is the one place that sets them: entered once where a run, an example or a benchmark
starts (``attnloop-slam`` around the whole command, :func:`slam.pipeline.run_slam` around its run), never
below. It restores the caller's counts afterwards: a library must not change its caller's process state
for good. The library's workers (the frame readers, the loop worker, the map worker) are Python threads,
each computing with the process-wide counts the context set. torch's inter-op pool is left alone (it can
only be sized before its first use, and the pipeline does not use it). BLAS and OpenMP go through
``threadpoolctl``, with scipy's BLAS loaded first so that the pose graph's LAPACK calls are covered too.

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
import numbers
from collections.abc import Iterator

import cv2
import torch
from threadpoolctl import threadpool_info, threadpool_limits

__all__ = ["check_threads", "limit_threads", "thread_counts"]


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
    """The current counts: ``{"torch": int, "opencv": int, "blas": [int, ...]}`` (one per BLAS library loaded)."""
    return {"torch": torch.get_num_threads(), "opencv": cv2.getNumThreads(),
            "blas": [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]}


@contextlib.contextmanager
def limit_threads(n: int | None) -> Iterator[None]:
    """torch, BLAS, OpenMP and OpenCV compute with ``n`` threads inside the block; the previous counts after.

    Args:
        n: the thread count (>= 1), or None to change nothing.

    Raises:
        ValueError: ``n`` is not None or a whole number >= 1.
    """
    n = check_threads(n)
    if n is None:
        yield
        return
    import scipy.linalg  # noqa: F401  (scipy's own BLAS, which the pose graph calls, loaded before the limit)

    prev_torch, prev_cv = torch.get_num_threads(), cv2.getNumThreads()
    torch.set_num_threads(n)
    cv2.setNumThreads(n)
    try:
        with threadpool_limits(limits=n):
            yield
    finally:
        cv2.setNumThreads(prev_cv)
        torch.set_num_threads(prev_torch)
