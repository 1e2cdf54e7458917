"""The thread count of the BLAS libraries loaded in this process (numpy's and scipy's OpenBLAS, MKL, BLIS),
set for a block of code through ``threadpoolctl``.

Why: the sparse Cholesky of the pose-graph optimiser makes many small LAPACK/BLAS calls, and OpenBLAS
threads some of them (e.g. a 60 x 18 ``trsm``), which on a busy CPU took 16 ms instead of 3 us.
``threadpoolctl`` (the optional extra ``attnloop[accel]``) finds the libraries and sets their pools;
without it :class:`limit_blas_threads` changes nothing (BLAS keeps its own count) and
:func:`blas_thread_control` says so.

The libraries are looked up once (a ``ThreadpoolController`` takes ~20 ms to build), after scipy's BLAS
is loaded; a nested limit to the same count in the same thread costs nothing (the sparse solver sets one
thread per factorisation, usually inside an ``optimize`` call that already did).

Example:
    >>> import numpy as np
    >>> with limit_blas_threads(1):
    ...     float(np.ones((64, 64)) @ np.ones(64) @ np.ones(64))
    4096.0
"""
from __future__ import annotations

import threading
from typing import List, Optional

__all__ = ["blas_thread_control", "limit_blas_threads"]

_LIBS: Optional[List] = None  # threadpoolctl's controllers of the BLAS libraries ([] without threadpoolctl)
_LOCK = threading.Lock()
_LOCAL = threading.local()  # .limit: the count an enclosing limit_blas_threads set in this thread


def _blas_libraries() -> List:
    """The ``threadpoolctl`` controllers of the loaded BLAS libraries, found once ([] without threadpoolctl)."""
    global _LIBS
    if _LIBS is None:
        with _LOCK:
            if _LIBS is None:
                try:
                    from threadpoolctl import ThreadpoolController
                except ImportError:
                    _LIBS = []
                else:
                    import scipy.linalg.blas  # noqa: F401  (load scipy's BLAS before looking)

                    _LIBS = [lib for lib in ThreadpoolController().lib_controllers if lib.user_api == "blas"]
    return _LIBS


def blas_thread_control() -> bool:
    """Whether :class:`limit_blas_threads` can set the BLAS thread count here (``threadpoolctl`` is
    installed and found a BLAS library)."""
    return bool(_blas_libraries())


class limit_blas_threads:
    """Context manager: the BLAS libraries use ``n`` threads inside, their previous counts after.

    Args:
        n: the thread count, or None to change nothing.
    """

    def __init__(self, n: Optional[int]):
        if n is not None and int(n) < 1:
            raise ValueError(f"n must be >= 1 or None, got {n}")
        self.n = None if n is None else int(n)
        self._saved: list = []
        self._outer: Optional[int] = None

    def __enter__(self) -> limit_blas_threads:
        self._outer = getattr(_LOCAL, "limit", None)
        if self.n is None or self.n == self._outer:
            return self
        for lib in _blas_libraries():
            old = lib.get_num_threads()
            if old is not None and old != self.n:
                lib.set_num_threads(self.n)
                self._saved.append((lib, old))
        _LOCAL.limit = self.n
        return self

    def __exit__(self, *exc) -> bool:
        for lib, old in reversed(self._saved):
            lib.set_num_threads(old)
        self._saved = []
        _LOCAL.limit = self._outer
        return False
