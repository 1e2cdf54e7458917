"""The approximate structures behind :class:`attnloop.index.KeyframeIndex`: a FLANN tree and a faiss HNSW graph.

A structure covers rows ``[0, n)`` of the index's store and proposes candidate rows, which the index
re-scores exactly: ``build(x, config)``; ``candidates(q, k, m)``: up to ``k`` rows ``< m`` near the unit query
``q (D,)``, or None where a scan of the prefix is cheaper; ``extendable``: then ``extend(x)`` and ``stale()``
(the PCA code calls for a rebuild); ``state()`` / ``from_state(meta, arrays, x, config)``: a faithful copy.
"""
from __future__ import annotations

import os
import struct
import tempfile

import cv2
import numpy as np

from attnloop.index.config import IndexConfig
from attnloop.index.reduction import PCACode, fit_pca

__all__ = ["STRUCTURES", "FaissHNSW", "FlannTree", "import_faiss"]

_FLANN_INDEX_KMEANS = 2
_ADD_CHUNK = 16384  # rows converted/encoded at a time when building (bounds float32 temporaries)


def import_faiss():
    """``faiss``, or an ImportError that says how to install it."""
    try:
        import faiss
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("the 'faiss' index backend needs faiss: pip install 'attnloop[faiss]'") from exc
    return faiss


def _fit_code(x: np.ndarray, config: IndexConfig) -> PCACode | None:
    return None if config.reduce_dim is None else fit_pca(x, config.reduce_dim, seed=config.seed)


def _codes(x: np.ndarray, code: PCACode | None) -> np.ndarray:
    """What the structure indexes: contiguous float32 codes (or descriptors, without a code)."""
    return np.ascontiguousarray(x, dtype=np.float32) if code is None else code.encode(x)


def _code_state(code: PCACode | None) -> dict:
    return {} if code is None else {f"pca.{k}": v for k, v in code.state().items()}


def _code_from_state(arrays: dict, dim: int, config: IndexConfig) -> PCACode | None:
    """The saved PCA code, checked against the descriptors' dimension ``dim`` and ``config.reduce_dim``."""
    sub = {k[4:]: v for k, v in arrays.items() if k.startswith("pca.")}
    if config.reduce_dim is None:
        if sub:
            raise ValueError("the saved structure has a PCA code but its config has reduce_dim=None")
        return None
    if not sub:
        raise ValueError(f"the saved structure lacks its PCA code (config reduce_dim={config.reduce_dim})")
    code = PCACode.from_state(sub, dim)
    if code.dim > config.reduce_dim:
        raise ValueError(f"the saved PCA code has {code.dim} components, more than reduce_dim={config.reduce_dim}")
    return code


def _blob(arrays: dict) -> np.ndarray:
    blob = arrays.get("blob")
    if blob is None:
        raise ValueError("the saved structure lacks its 'structure.blob'")
    blob = np.asarray(blob)
    if blob.dtype != np.uint8 or blob.ndim != 1 or blob.size == 0:
        raise ValueError(f"'structure.blob' must be a non-empty 1-D uint8 array, got {blob.dtype} "
                         f"{tuple(blob.shape)}")
    return blob


# FLANN's file header (cvflann::IndexHeader): signature, version, data type, algorithm, rows, cols.
_FLANN_HEADER = struct.Struct("=16s16siiQQ")
_FLANN_FLOAT32 = 8


class FlannTree:
    """FLANN priority-search k-means tree over rows ``[0, n)`` (not extendable: rows after it are a tail).

    FLANN does not copy the data it indexes: ``_data`` is kept alive with the tree.
    """

    kind = "flann"
    extendable = False

    def __init__(self, flann, data: np.ndarray, code: PCACode | None, config: IndexConfig) -> None:
        self.flann = flann
        self._data = data
        self.code = code
        self.config = config  # read at query time: a caller may change checks between queries
        self.n = int(data.shape[0])

    @classmethod
    def build(cls, x: np.ndarray, config: IndexConfig) -> FlannTree:
        code = _fit_code(x, config)
        data = _codes(x, code)
        # OpenCV's RNG is thread-local: seeding in the worker thread leaves the caller's alone
        cv2.setRNGSeed(int(config.seed))
        f = config.flann
        params = {"algorithm": _FLANN_INDEX_KMEANS, "branching": int(f.branching), "iterations": int(f.iterations)}
        return cls(cv2.flann_Index(data, params), data, code, config)

    def candidates(self, q: np.ndarray, k: int, m: int) -> np.ndarray | None:
        # rows past the prefix are asked for and filtered out, unless a scan of the prefix is cheaper
        excess = max(0, self.n - m)
        if excess > max(4 * k, 64):
            return None
        kq = min(k + excess, self.n)
        qc = q[None] if self.code is None else self.code.encode(q[None])
        idx, _ = self.flann.knnSearch(qc, kq, params={"checks": int(self.config.flann.checks)})
        idx = idx[0].astype(np.int64)
        return idx[(idx >= 0) & (idx < min(m, self.n))]

    def state(self) -> tuple[dict, dict]:
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "tree.flann")
            self.flann.save(path)
            with open(path, "rb") as f:
                blob = np.frombuffer(f.read(), dtype=np.uint8)
        return {"kind": self.kind, "n": self.n}, {"blob": blob, **_code_state(self.code)}

    @classmethod
    def from_state(cls, meta: dict, arrays: dict, x: np.ndarray, config: IndexConfig) -> FlannTree:
        """The saved tree over rows ``[0, meta["n"])`` of ``x``; ValueError when the blob's header or the PCA
        code disagree with the record."""
        n = int(meta["n"])
        code = _code_from_state(arrays, x.shape[1], config)
        blob = _blob(arrays)
        if blob.size < _FLANN_HEADER.size:
            raise ValueError(f"the saved FLANN tree is {blob.size} bytes, shorter than its header")
        sig, _, dtype, algo, rows, cols = _FLANN_HEADER.unpack_from(blob.tobytes()[: _FLANN_HEADER.size])
        if not sig.startswith(b"FLANN_INDEX"):
            raise ValueError("the saved FLANN tree lacks FLANN's signature (not a FLANN index)")
        dim = x.shape[1] if code is None else code.dim
        if (dtype, algo, rows, cols) != (_FLANN_FLOAT32, _FLANN_INDEX_KMEANS, n, dim):
            raise ValueError(f"the saved FLANN tree is algorithm {algo}, data type {dtype}, over {rows} rows of "
                             f"dimension {cols}; the record needs a k-means tree ({_FLANN_INDEX_KMEANS}) of "
                             f"float32 ({_FLANN_FLOAT32}) over {n} rows of dimension {dim}")
        data = _codes(x[:n], code)
        flann = cv2.flann_Index()
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "tree.flann")
            with open(path, "wb") as f:
                f.write(blob.tobytes())
            if not flann.load(data, path):
                raise ValueError("the saved FLANN tree could not be loaded")
        return cls(flann, data, code, config)


class FaissHNSW:
    """faiss HNSW graph over rows ``[0, n)``, extended by every add (rows are its sequential ids)."""

    kind = "faiss"
    extendable = True

    def __init__(self, index, n_trained: int, code: PCACode | None, config: IndexConfig) -> None:
        self.index = index
        self.code = code
        self.config = config  # read at query time: a caller may change ef_search between queries
        self.n_trained = int(n_trained)

    @property
    def n(self) -> int:
        return int(self.index.ntotal)

    @classmethod
    def build(cls, x: np.ndarray, config: IndexConfig) -> FaissHNSW:
        faiss = import_faiss()
        code = _fit_code(x, config)
        index = faiss.IndexHNSWFlat(x.shape[1] if code is None else code.dim, int(config.faiss.m))
        index.hnsw.efConstruction = int(config.faiss.ef_construction)
        for lo in range(0, x.shape[0], _ADD_CHUNK):
            index.add(_codes(x[lo: lo + _ADD_CHUNK], code))
        return cls(index, x.shape[0], code, config)

    def candidates(self, q: np.ndarray, k: int, m: int) -> np.ndarray:
        faiss = import_faiss()
        qc = q[None] if self.code is None else self.code.encode(q[None])
        ef = max(int(self.config.faiss.ef_search), k)
        if m >= self.n:
            params = faiss.SearchParametersHNSW(efSearch=ef)
            _, idx = self.index.search(qc, min(k, self.n), params=params)
        else:  # the exclusion window: rows are ids 0..n-1, so the eligible prefix is an id range
            sel = faiss.IDSelectorRange(0, int(m))
            # the excluded (most recent, nearest) rows on top of ef eligible ones; a deep cut leaves ~m/n eligible
            excess = self.n - int(m)
            ef = ef + excess if excess <= 4 * ef else -(-ef * self.n // int(m))
            ef = min(self.n, ef)
            params = faiss.SearchParametersHNSW(sel=sel, efSearch=ef)
            _, idx = self.index.search(qc, min(k, m), params=params)
        idx = idx[0].astype(np.int64)
        return idx[(idx >= 0) & (idx < m)]

    def extend(self, x: np.ndarray) -> None:
        self.index.add(_codes(x, self.code))

    def stale(self) -> bool:
        """Whether the PCA code calls for a refit: the rows have grown by ``retrain_growth`` since it."""
        return self.code is not None and self.n - self.n_trained >= self.config.faiss.retrain_growth * self.n_trained

    def state(self) -> tuple[dict, dict]:
        faiss = import_faiss()
        meta = {"kind": self.kind, "n": self.n, "n_trained": self.n_trained}
        return meta, {"blob": faiss.serialize_index(self.index), **_code_state(self.code)}

    @classmethod
    def from_state(cls, meta: dict, arrays: dict, x: np.ndarray, config: IndexConfig) -> FaissHNSW:
        """The saved graph; ValueError unless an L2 HNSW graph over the record's rows and dimension."""
        faiss = import_faiss()
        n, n_trained = int(meta["n"]), meta.get("n_trained")
        if not isinstance(n_trained, int) or isinstance(n_trained, bool) or not 1 <= n_trained <= n:
            raise ValueError(f"the HNSW record's n_trained must be an integer in [1, {n}], got {n_trained!r}")
        code = _code_from_state(arrays, x.shape[1], config)
        index = faiss.deserialize_index(_blob(arrays))  # returned as its own class (IndexHNSWFlat)
        if not isinstance(index, faiss.IndexHNSWFlat) or index.metric_type != faiss.METRIC_L2:
            raise ValueError(f"the saved structure is a {type(index).__name__}, not an L2 faiss IndexHNSWFlat")
        dim = x.shape[1] if code is None else code.dim
        if int(index.ntotal) != n or int(index.d) != dim:
            raise ValueError(f"the saved HNSW graph holds {index.ntotal} rows of dimension {index.d}, its record "
                             f"says {n} rows of dimension {dim}")
        return cls(index, n_trained, code, config)


STRUCTURES = {"flann": FlannTree, "faiss": FaissHNSW}
