"""The thread counts a run computes with: torch's intra-op pool, the BLAS and OpenMP libraries' and OpenCV's.

:func:`limit_threads` is the one place that sets them (``SLAMConfig.threads``, 1 by default: a pool larger than
the free cores waits for a descheduled thread at every barrier; docs/results.md, "Threads"), and restores the
caller's afterwards. torch's inter-op pool is left alone (it can only be sized before its first use).

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
