"""Keyframe index for loop closure: which earlier keyframes look like this one, from one to a million.

:class:`KeyframeIndex` (backends, persistence: docs/scale.md), :class:`LoopCandidateDetector` (search and
adaptive threshold) and :func:`exact_search`, the brute-force reference.
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
