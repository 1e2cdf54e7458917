"""Configuration of the keyframe index: :class:`IndexConfig` and the settings of each backend."""
from __future__ import annotations

import dataclasses
import importlib.util
import math
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "BACKENDS", "STORAGE_DTYPES", "FaissConfig", "FlannConfig", "IndexConfig", "config_from_dict",
    "config_to_dict", "faiss_available", "resolve_backend",
]

BACKENDS = ("auto", "exact", "flann", "faiss")
STORAGE_DTYPES = ("float32", "float16")


@dataclass(frozen=True)
class FlannConfig:
    """The paper's FLANN priority-search k-means tree (OpenCV's ``cv2.flann_Index``), rebuilt as rows are added."""

    branching: int = 32  # k-means tree branching factor (FLANN's default)
    iterations: int = 5  # k-means iterations per node
    checks: int = 512  # points examined per query; -1 = exhaustive tree search (exact)
    rebuild_every: int = 256  # rebuild the tree once the unindexed tail holds this many rows ...
    rebuild_fraction: float = 0.25  # ... and at least this fraction of the indexed rows

    def __post_init__(self) -> None:
        if self.branching < 2:
            raise ValueError(f"FlannConfig.branching must be >= 2, got {self.branching}")
        if self.iterations < 1:
            raise ValueError(f"FlannConfig.iterations must be >= 1, got {self.iterations}")
        if self.checks == 0 or self.checks < -1:
            raise ValueError(f"FlannConfig.checks must be positive or -1 (exhaustive), got {self.checks}")
        if self.rebuild_every < 1 or self.rebuild_fraction < 0:
            raise ValueError("FlannConfig.rebuild_every must be >= 1 and rebuild_fraction >= 0")


@dataclass(frozen=True)
class FaissConfig:
    """A faiss HNSW graph (``faiss.IndexHNSWFlat``, L2 on the unit descriptors or their PCA codes), grown by
    every ``add`` and rebuilt only to refit its PCA code. Settings measured: docs/results.md, "Keyframe index"."""

    m: int = 64  # links per node (2 m on the bottom layer)
    ef_construction: int = 80  # candidate list while inserting
    ef_search: int = 64  # candidate list while searching (raised to the number of rows asked for)
    # refit the PCA code and rebuild once the rows added since the fit reach this fraction of the rows it was
    # fitted on (1.0: at every doubling; inf: never)
    retrain_growth: float = 1.0

    def __post_init__(self) -> None:
        if self.m < 2 or self.ef_construction < 1 or self.ef_search < 1:
            raise ValueError(f"FaissConfig: need m >= 2, ef_construction >= 1, ef_search >= 1, got {self.m}, "
                             f"{self.ef_construction}, {self.ef_search}")
        if not self.retrain_growth > 0:
            raise ValueError(f"FaissConfig.retrain_growth must be > 0 (inf: never), got {self.retrain_growth}")


@dataclass(frozen=True)
class IndexConfig:
    """Parameters of :class:`attnloop.index.KeyframeIndex` (``"auto"``: ``"faiss"`` where installed, else
    ``"flann"``)."""

    backend: str = "auto"  # "auto" | "exact" | "flann" | "faiss" (BACKENDS)
    exact_below: int = 4096  # below this many eligible keyframes a plain scan answers; no structure is built
    reduce_dim: int | None = 128  # PCA code the structure is built on (None: the full descriptors)
    rerank: int = 8  # the structure proposes rerank * k rows per query, all re-scored exactly
    storage: str = "float32"  # dtype of the stored descriptors: "float32" | "float16" (half the memory)
    background: bool = True  # build structures in a worker thread; queries use the old one meanwhile
    seed: int = 0  # seed of the k-means centres (flann) and of the PCA's fitting sample
    flann: FlannConfig = field(default_factory=FlannConfig)
    faiss: FaissConfig = field(default_factory=FaissConfig)

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"IndexConfig.backend must be one of {BACKENDS}, got {self.backend!r}")
        if self.storage not in STORAGE_DTYPES:
            raise ValueError(f"IndexConfig.storage must be one of {STORAGE_DTYPES}, got {self.storage!r}")
        if self.exact_below < 1:
            raise ValueError(f"IndexConfig.exact_below must be >= 1, got {self.exact_below}")
        if self.reduce_dim is not None and self.reduce_dim < 1:
            raise ValueError(f"IndexConfig.reduce_dim must be None or >= 1, got {self.reduce_dim}")
        if self.rerank < 1:
            raise ValueError(f"IndexConfig.rerank must be >= 1, got {self.rerank}")


def faiss_available() -> bool:
    """Whether ``faiss`` can be imported (``pip install attnloop[faiss]``)."""
    return importlib.util.find_spec("faiss") is not None


def resolve_backend(backend: str) -> str:
    """The backend that ``backend`` names here: ``"auto"`` -> ``"faiss"`` if installed, else ``"flann"``.

    Raises:
        ValueError: an unknown name.
        ImportError: ``"faiss"`` asked for where faiss is not installed.
    """
    if backend not in BACKENDS:
        raise ValueError(f"index backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        return "faiss" if faiss_available() else "flann"
    if backend == "faiss" and not faiss_available():
        raise ImportError("IndexConfig(backend='faiss') needs faiss: pip install 'attnloop[faiss]' "
                          "(or faiss-cpu); backend='auto' falls back to 'flann' without it")
    return backend


def config_to_dict(config: IndexConfig) -> dict:
    """A JSON-friendly dict of ``config`` (nested backend settings as dicts; ``inf`` as the string "inf")."""
    out = dataclasses.asdict(config)
    growth = out["faiss"]["retrain_growth"]
    out["faiss"]["retrain_growth"] = "inf" if math.isinf(growth) else growth
    return out


#: Settings of files saved by earlier versions, with the one value still meant.
_RETIRED = {"whiten": False, "normalize": True}


def config_from_dict(data: dict) -> IndexConfig:
    """Inverse of :func:`config_to_dict`; ValueError naming unknown keys."""
    data = dict(data)
    for key, kept in _RETIRED.items():
        if key in data and data.pop(key) != kept:
            raise ValueError(f"IndexConfig.{key} is no longer supported (only {key}={kept} is)")
    nested = {"flann": FlannConfig, "faiss": FaissConfig}
    kwargs: dict[str, Any] = {}
    for name, cls in nested.items():
        if name in data:
            sub = dict(data.pop(name))
            _check_keys(sub, cls, f"IndexConfig.{name}")
            if "retrain_growth" in sub:
                sub["retrain_growth"] = float(sub["retrain_growth"])
            kwargs[name] = cls(**sub)
    _check_keys(data, IndexConfig, "IndexConfig")
    return IndexConfig(**data, **kwargs)


def _check_keys(data: dict, cls, what: str) -> None:
    unknown = set(data) - {f.name for f in dataclasses.fields(cls)}
    if unknown:
        raise ValueError(f"{what} has no setting(s) {sorted(unknown)}")
