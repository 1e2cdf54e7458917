"""Keyframe index for loop closure: which earlier keyframes look like this one, from one to a million.

- :class:`KeyframeIndex`: the database. ``KeyframeIndex(IndexConfig(backend=...)).add(descriptors, ids=...)``,
  ``.search(query, k=..., max_id=...)`` (the temporal exclusion window), ``.similarities(...)``,
  ``.save(path)`` / ``KeyframeIndex.load(path)``. Backends (:data:`BACKENDS`): ``"exact"`` (a scan),
  ``"flann"`` (the paper's FLANN priority-search k-means tree), ``"faiss"`` (an HNSW graph, optional
  ``pip install attnloop[faiss]``), and ``"auto"`` (the default: exact below ``exact_below`` keyframes,
  then faiss where installed, else flann). Candidates are always re-scored exactly; the structures can
  be built on a PCA code of the descriptors (``reduce_dim``).
- :class:`LoopCandidateDetector`: per new keyframe, search + adaptive threshold + temporal consistency.
- :func:`exact_search`: the brute-force reference.

Figures (recall, time per query, build time, memory from 10^4 to 10^6 keyframes): docs/results.md,
"Keyframe index"; beyond one machine: docs/scale.md.
"""
from __future__ import annotations

from attnloop.index.config import (
    BACKENDS,
    STORAGE_DTYPES,
    FaissConfig,
    FlannConfig,
    IndexConfig,
    faiss_available,
    resolve_backend,
)
from attnloop.index.database import KeyframeIndex, load_index
from attnloop.index.detector import LoopCandidateDetector, LoopCandidates, LoopDetectorConfig
from attnloop.index.exact import exact_search
from attnloop.index.persistence import IndexFileError, save_index
from attnloop.index.reduction import PCACode, fit_pca

__all__ = [
    "BACKENDS", "STORAGE_DTYPES", "FaissConfig", "FlannConfig", "IndexConfig", "IndexFileError",
    "KeyframeIndex", "LoopCandidateDetector", "LoopCandidates", "LoopDetectorConfig", "PCACode",
    "exact_search", "faiss_available", "fit_pca", "load_index", "resolve_backend", "save_index",
]
