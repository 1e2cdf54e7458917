"""The rows of a keyframe index: descriptors (float32 or float16), ids and timestamps, growing by doubling.

A grown buffer is a fresh array and rows are never rewritten, so a view a background build holds stays valid.
"""
from __future__ import annotations

import numpy as np
import torch

from attnloop.index.exact import matvec

__all__ = ["KeyframeStore"]

# float16 rows are widened to float32 this many at a time before a product (a float16 product rounds to float16)
_CHUNK = 16384
GATHER_BYTES = 1 << 22  # rows gathered (copied) at a time by matvec_rows and the re-scoring: ~4 MB


class KeyframeStore:
    """Growing ``(N, D)`` descriptor buffer with ``(N,)`` ids and timestamps.

    Args:
        dim: descriptor size ``D``.
        dtype: ``"float32"`` or ``"float16"`` (the descriptors' storage; every product is float32).
    """

    def __init__(self, dim: int, dtype: str = "float32") -> None:
        self.dim = int(dim)
        self.dtype = np.dtype(dtype)
        self.n = 0
        self._desc = np.zeros((0, self.dim), dtype=self.dtype)
        self._ids = np.zeros(0, dtype=np.int64)
        self._ts = np.zeros(0, dtype=np.float64)

    def append(self, x: np.ndarray, ids: np.ndarray, timestamps: np.ndarray) -> None:
        """Append rows ``x (M, D)`` (float32) with their ids and timestamps ``(M,)``."""
        m = x.shape[0]
        if self.n + m > self._desc.shape[0]:  # grown into fresh arrays: earlier views stay valid
            new_cap = max(self.n + m, 2 * self._desc.shape[0], 1024)
            grown = (np.empty((new_cap, self.dim), dtype=self.dtype), np.empty(new_cap, dtype=np.int64),
                     np.empty(new_cap, dtype=np.float64))
            for new, old in zip(grown, (self._desc, self._ids, self._ts)):
                new[: self.n] = old[: self.n]
            self._desc, self._ids, self._ts = grown
        self._desc[self.n: self.n + m] = x
        self._ids[self.n: self.n + m] = ids
        self._ts[self.n: self.n + m] = timestamps
        self.n += m

    @property
    def ids(self) -> np.ndarray:
        """Ids of rows ``[0, N)`` (a view)."""
        return self._ids[: self.n]

    @property
    def timestamps(self) -> np.ndarray:
        """Timestamps of rows ``[0, N)`` (a view)."""
        return self._ts[: self.n]

    @property
    def nbytes(self) -> int:
        """Bytes of the valid rows (descriptors, ids, timestamps)."""
        return self.n * (self.dim * self.dtype.itemsize + 16)

    def view(self, start: int = 0) -> np.ndarray:
        """Stored descriptors of rows ``[start, N)``, in the storage dtype (a view, never written again)."""
        return self._desc[start: self.n]

    def rows(self, rows: np.ndarray, dtype=np.float32) -> np.ndarray:
        """Descriptors of the given rows ``(M,)`` as ``(M, D)`` of ``dtype`` (float32 by default)."""
        return self._desc[rows].astype(dtype, copy=False)

    def row_norms(self) -> np.ndarray:
        """L2 norms ``(N,)`` (float64) of the rows, computed a chunk at a time."""
        out = np.empty(self.n, dtype=np.float64)
        step = 4 * GATHER_BYTES // (8 * max(1, self.dim)) + 1  # float64 temporaries of ~16 MB
        for lo in range(0, self.n, step):
            chunk = torch.from_numpy(self._desc[lo: min(lo + step, self.n)]).double()
            out[lo: lo + chunk.shape[0]] = torch.linalg.vector_norm(chunk, dim=1).numpy()
        return out

    def matvec_rows(self, q: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Similarities ``(M,)`` (float32) of ``q (D,)`` to the given rows ``(M,)``, gathered a chunk at a time."""
        out = np.empty(rows.size, dtype=np.float32)
        chunk = GATHER_BYTES // max(1, 4 * self.dim) + 1
        for lo in range(0, rows.size, chunk):
            block = np.take(self._desc, rows[lo: lo + chunk], axis=0)  # faster than fancy indexing
            out[lo: lo + chunk] = matvec(block.astype(np.float32, copy=False), q)
        return out

    def matvec(self, q: np.ndarray, start: int, stop: int) -> np.ndarray:
        """Similarities ``(M,)`` (float32) of ``q (D,)`` to rows ``[start, stop)``."""
        if self.dtype == np.float32:
            return matvec(self._desc[start:stop], q)
        out = np.empty(max(0, stop - start), dtype=np.float32)
        qt = torch.from_numpy(q)
        for lo in range(start, stop, _CHUNK):
            chunk = torch.from_numpy(self._desc[lo: min(lo + _CHUNK, stop)]).float()
            out[lo - start: lo - start + chunk.shape[0]] = (chunk @ qt).numpy()
        return out
