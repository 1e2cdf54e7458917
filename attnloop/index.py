"""Keyframe database for loop closure: a FLANN priority-search k-means tree plus an exact tail.

Descriptors are L2-normalised, so the cosine similarity is a dot product and the Euclidean distance that
FLANN ranks by is ``|a - b|^2 = 2 - 2 a.b``: the nearest neighbours in L2 are the most similar keyframes.

**Growth.** FLANN cannot add points to a k-means tree, so the database is split in two:

* all descriptors live in one growing float32 buffer (capacity doubles; rows are never modified);
* the tree covers the first ``n_indexed`` rows; the rows after it (the *tail*) are scanned exactly with a
  matrix product;
* when the tail holds ``max(rebuild_every, rebuild_fraction * n_indexed)`` rows, a new tree over all rows
  is built, by default in a background thread (OpenCV releases the GIL while building, so tracking goes
  on); until it is ready, queries keep using the old tree plus the (longer) exact tail, and the new tree
  is swapped in atomically (one attribute assignment) by the next ``add``/``search``. With the fraction,
  the number of rebuilds grows only logarithmically with the database size.
* below ``min_tree_size`` rows no tree is built: an exact scan is faster there.

**Exactness.** Every answer is re-scored exactly (dot products of the returned rows) and merged with the
exact tail, so the only approximation is the tree's own search, controlled by ``checks`` (points examined).
With ``checks=-1`` FLANN searches the k-means tree exhaustively with ball pruning, and the answer equals a
brute-force search over the eligible keyframes (up to float32 rounding of near-ties); ``exact=True``
skips the tree altogether.

**Exclusion window.** Keyframe ids must increase with every ``add``; ``search(..., max_id=m)`` only returns
keyframes with ``id <= m`` (for a query keyframe ``q`` and a window ``w``: ``m = q - w`` excludes the ``w``
most recent ids). Because ids increase, the eligible keyframes are a prefix of the buffer; tree results
past the prefix are filtered out after asking the tree for that many extra neighbours, so exactness is kept.

Example:
    >>> index = KeyframeIndex(IndexConfig(min_tree_size=64, background=False))
    >>> data = torch.randn(200, 32)
    >>> index.add(data, ids=torch.arange(200))
    >>> ids, sims = index.search(data[150], k=3, max_id=140)
    >>> ids.shape, sims.shape, bool((ids <= 140).all())
    (torch.Size([3]), torch.Size([3]), True)
    >>> index.search(data[0], k=3, max_id=-1)[0].shape
    torch.Size([0])
"""
from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple

import cv2
import numpy as np
import torch

from attnloop.threshold import ThresholdConfig, adaptive_threshold

Tensor = torch.Tensor

__all__ = [
    "IndexConfig", "KeyframeIndex", "LoopCandidateDetector", "LoopCandidates", "LoopDetectorConfig",
    "exact_search",
]

_FLANN_INDEX_KMEANS = 2


# ----------------------------------------------------------------------------------------------
# Configuration
# ----------------------------------------------------------------------------------------------
@dataclass
class IndexConfig:
    """Parameters of :class:`KeyframeIndex`.

    OpenCV's Python binding cannot pass FLANN's ``centers_init`` (a C++ enum), so the k-means centres are
    always initialised at random (FLANN's default), from OpenCV's RNG seeded with ``seed`` in the build
    thread (the caller's RNG is untouched).
    """

    branching: int = 32  # k-means tree branching factor (FLANN's default)
    iterations: int = 5  # k-means iterations per node (FLANN default 11; 5 builds ~2x faster, same recall)
    checks: int = 512  # points examined per query; -1 = exhaustive tree search (exact); docs/benchmarks
    min_tree_size: int = 2048  # below this many rows a plain exact scan is used (faster than a tree)
    rebuild_every: int = 256  # rebuild the tree once the unindexed tail holds this many rows ...
    rebuild_fraction: float = 0.25  # ... and at least this fraction of the indexed rows
    background: bool = True  # build in a worker thread; queries use the old tree + exact tail meanwhile
    exact: bool = False  # never use the tree: brute-force scan (the reference)
    normalize: bool = True  # L2-normalise added descriptors and queries (similarity = cosine)
    seed: int = 0  # seed of the k-means centre initialisation

    def __post_init__(self) -> None:
        if self.branching < 2:
            raise ValueError(f"IndexConfig.branching must be >= 2, got {self.branching}")
        if self.checks == 0 or self.checks < -1:
            raise ValueError(f"IndexConfig.checks must be positive or -1 (exhaustive), got {self.checks}")
        if self.rebuild_every < 1 or self.rebuild_fraction < 0:
            raise ValueError("IndexConfig.rebuild_every must be >= 1 and rebuild_fraction >= 0")


@dataclass
class LoopDetectorConfig:
    """Parameters of :class:`LoopCandidateDetector`.

    Per query keyframe ``q``: the eligible keyframes are those with ``id <= q - window``; the ``top_k``
    most similar are taken from the index; a candidate is accepted when its similarity exceeds the
    adaptive threshold of the query's similarity distribution (:mod:`attnloop.threshold`, estimated on at
    most ``threshold_samples`` eligible keyframes spread evenly over the database) and, if
    ``consistency > 1``, when each of the ``consistency - 1`` previous queries also had a candidate
    above its threshold within ``consistency_radius`` ids of it (a revisit lasts several keyframes).
    """

    top_k: int = 5  # neighbours taken from the index per query
    window: int = 30  # exclusion window in keyframe ids: ids > query_id - window are never candidates
    consistency: int = 1  # consecutive queries that must agree (1 = off)
    consistency_radius: int = 5  # ids within this distance count as the same place for consistency
    threshold_samples: int = 4096  # max eligible keyframes used to estimate the similarity distribution
    threshold: ThresholdConfig = field(default_factory=ThresholdConfig)
    index: IndexConfig = field(default_factory=IndexConfig)

    def __post_init__(self) -> None:
        if self.top_k < 1 or self.window < 0 or self.consistency < 1 or self.consistency_radius < 0:
            raise ValueError("LoopDetectorConfig: need top_k >= 1, window >= 0, consistency >= 1, "
                             "consistency_radius >= 0")
        if self.threshold_samples < self.threshold.min_samples:
            raise ValueError("LoopDetectorConfig.threshold_samples must be >= threshold.min_samples")


# ----------------------------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------------------------
def _to_numpy_2d(x, name: str) -> tuple[np.ndarray, bool]:
    """(N, D) or (D,) tensor/array -> contiguous float32 (N, D) numpy array, and whether it was 1-D."""
    if isinstance(x, Tensor):
        arr = x.detach().to(device="cpu", dtype=torch.float32).numpy()
    else:
        arr = np.asarray(x, dtype=np.float32)
    if arr.ndim == 1:
        return np.ascontiguousarray(arr[None]), True
    if arr.ndim != 2:
        raise ValueError(f"{name} must have shape (D,) or (N, D), got {tuple(arr.shape)}")
    return np.ascontiguousarray(arr), False


def _as_array(x, dtype) -> np.ndarray:
    return np.asarray(x.detach().cpu().numpy() if isinstance(x, Tensor) else x, dtype=dtype)


def _matvec(a: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``a @ q`` for float32 ``a (M, D)`` (a view, possibly row-strided) and ``q (D,)``.

    Through torch: numpy's gemv was up to 10x slower and erratic on a busy 2-core machine.
    """
    if a.shape[0] == 0:
        return np.zeros(0, dtype=np.float32)
    return (torch.from_numpy(a) @ torch.from_numpy(q)).numpy()


def _l2_normalize(x: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(x, axis=1, keepdims=True)
    return x / np.maximum(norm, 1e-12)  # a zero descriptor stays zero (similarity 0 to everything)


def exact_search(database: Tensor, queries: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """Brute-force reference: the ``k`` rows of ``database`` with the largest dot product per query.

    Args:
        database: ``(N, D)``.
        queries: ``(Q, D)``.
        k: neighbours per query (clipped to ``N``).

    Returns:
        row indices ``(Q, min(k, N))`` (long) and similarities ``(Q, min(k, N))``, most similar first.

    Example:
        >>> rows, sims = exact_search(torch.eye(3), torch.tensor([[0.1, 0.9, 0.0]]), k=2)
        >>> rows.tolist()
        [[1, 0]]
    """
    if database.dim() != 2 or queries.dim() != 2 or database.shape[1] != queries.shape[1]:
        raise ValueError(f"need database (N, D) and queries (Q, D), got {tuple(database.shape)} and "
                         f"{tuple(queries.shape)}")
    kk = min(int(k), database.shape[0])
    sims = queries @ database.t()
    vals, rows = torch.topk(sims, kk, dim=1)
    return rows, vals


class _Tree(NamedTuple):
    """A built k-means tree over rows ``[0, n)`` of ``data`` (kept alive: FLANN does not copy it)."""

    flann: cv2.flann_Index
    n: int
    data: np.ndarray


def _build_tree(data: np.ndarray, cfg: IndexConfig) -> cv2.flann_Index:
    # Runs in a worker thread: OpenCV's RNG is thread-local, so seeding here is reproducible and leaves
    # the caller's RNG alone.
    cv2.setRNGSeed(int(cfg.seed))
    params = dict(algorithm=_FLANN_INDEX_KMEANS, branching=int(cfg.branching), iterations=int(cfg.iterations))
    return cv2.flann_Index(data, params)


# ----------------------------------------------------------------------------------------------
# The database
# ----------------------------------------------------------------------------------------------
class KeyframeIndex:
    """Growing keyframe database: k-means tree over the indexed rows + exact scan of the tail.

    Not safe for concurrent ``add``/``search`` calls from several threads (the SLAM loop calls it from
    one); the only concurrency is its own background tree build.

    Args:
        config: :class:`IndexConfig`.
        dim: descriptor size ``D``; inferred from the first ``add`` when ``None``.
    """

    def __init__(self, config: IndexConfig | None = None, dim: int | None = None) -> None:
        self.config = config or IndexConfig()
        self._dim = dim
        self._data = np.zeros((0, dim or 0), dtype=np.float32)  # capacity buffer, rows [0, n) valid
        self._ids = np.zeros(0, dtype=np.int64)
        self._timestamps = np.zeros(0, dtype=np.float64)
        self._n = 0
        self._tree: _Tree | None = None
        self._worker: threading.Thread | None = None
        self._result: list = []  # the worker's (tree | exception), read by _poll
        self.num_builds = 0

    # ------------------------------------------------------------------ properties
    def __len__(self) -> int:
        return self._n

    @property
    def dim(self) -> int | None:
        """Descriptor size ``D`` (``None`` before the first add)."""
        return self._dim

    @property
    def n_indexed(self) -> int:
        """Rows covered by the current tree (the rest is scanned exactly)."""
        tree = self._tree
        return 0 if tree is None else tree.n

    @property
    def building(self) -> bool:
        """Whether a background build is running."""
        return self._worker is not None and self._worker.is_alive()

    @property
    def ids(self) -> Tensor:
        """Keyframe ids ``(N,)`` (long), in insertion (= increasing) order."""
        return torch.from_numpy(self._ids[: self._n].copy())

    @property
    def timestamps(self) -> Tensor:
        """Timestamps ``(N,)`` (float64; NaN where none was given)."""
        return torch.from_numpy(self._timestamps[: self._n].copy())

    @property
    def descriptors(self) -> Tensor:
        """The stored (normalised) descriptors ``(N, D)``, a float32 copy."""
        return torch.from_numpy(self._data[: self._n].copy())

    def rows_of(self, ids) -> Tensor:
        """Buffer rows of the given keyframe ids ``(M,)``; ValueError naming an unknown id."""
        q = np.atleast_1d(_as_array(ids, np.int64))
        stored = self._ids[: self._n]
        rows = np.searchsorted(stored, q)
        ok = rows < self._n
        ok[ok] = stored[rows[ok]] == q[ok]
        if not np.all(ok):
            raise ValueError(f"unknown keyframe id(s) {q[~ok].tolist()[:5]} "
                             f"(the index holds {self._n} keyframes)")
        return torch.from_numpy(rows)

    # ------------------------------------------------------------------ growth
    def add(self, descriptors, ids=None, timestamps=None) -> None:
        """Append keyframes.

        Args:
            descriptors: ``(D,)`` or ``(M, D)`` tensor or array (any device; stored as CPU float32).
            ids: ``(M,)`` integer keyframe ids, strictly increasing and above every stored id; default
                continues from the last id (``0, 1, 2, ...``).
            timestamps: ``(M,)`` optional, stored for the caller.
        """
        x, _ = _to_numpy_2d(descriptors, "descriptors")
        m, d = x.shape
        if self._dim is None:
            self._dim = d
            self._data = np.zeros((0, d), dtype=np.float32)
        elif d != self._dim:
            raise ValueError(f"descriptors have dimension {d} but the index holds dimension {self._dim} "
                             f"(got shape {tuple(x.shape)})")
        if m == 0:
            return
        if not np.all(np.isfinite(x)):
            raise ValueError("descriptors contain NaN or inf")
        if ids is None:
            start = int(self._ids[self._n - 1]) + 1 if self._n else 0
            new_ids = np.arange(start, start + m, dtype=np.int64)
        else:
            new_ids = np.atleast_1d(_as_array(ids, np.int64))
            if new_ids.shape != (m,):
                raise ValueError(f"ids must have shape ({m},), got {tuple(new_ids.shape)}")
        last = self._ids[self._n - 1] if self._n else None
        if np.any(np.diff(new_ids) <= 0) or (last is not None and new_ids[0] <= last):
            raise ValueError(f"keyframe ids must be strictly increasing; got {new_ids[:5].tolist()}... "
                             f"after last id {last}")
        ts = np.full(m, np.nan) if timestamps is None else np.atleast_1d(_as_array(timestamps, np.float64))
        if ts.shape != (m,):
            raise ValueError(f"timestamps must have shape ({m},), got {tuple(ts.shape)}")
        if self.config.normalize:
            x = _l2_normalize(x)

        self._poll()
        self._reserve(self._n + m)
        self._data[self._n: self._n + m] = x
        self._ids[self._n: self._n + m] = new_ids
        self._timestamps[self._n: self._n + m] = ts
        self._n += m
        self._maybe_rebuild()

    def _reserve(self, n: int) -> None:
        cap = self._data.shape[0]
        if n <= cap:
            return
        new_cap = max(n, 2 * cap, 1024)
        # A fresh buffer: the old one stays alive as long as a tree built on it (rows < tree.n unchanged).
        data = np.empty((new_cap, self._dim), dtype=np.float32)
        data[: self._n] = self._data[: self._n]
        ids = np.empty(new_cap, dtype=np.int64)
        ids[: self._n] = self._ids[: self._n]
        ts = np.empty(new_cap, dtype=np.float64)
        ts[: self._n] = self._timestamps[: self._n]
        self._data, self._ids, self._timestamps = data, ids, ts

    def _needs_rebuild(self) -> bool:
        cfg = self.config
        if cfg.exact or self._n < cfg.min_tree_size:
            return False
        tail = self._n - self.n_indexed
        return tail >= max(cfg.rebuild_every, cfg.rebuild_fraction * self.n_indexed)

    def _maybe_rebuild(self) -> None:
        if self._needs_rebuild() and not self.building:
            self._start_build(background=self.config.background)

    def _start_build(self, background: bool) -> None:
        n, data = self._n, self._data
        snapshot = data[:n]  # a contiguous view; rows [0, n) are never written again
        result: list = []

        def work() -> None:
            try:
                result.append(_Tree(_build_tree(snapshot, self.config), n, data))
            except BaseException as exc:  # surfaced in the caller's thread by _poll
                result.append(exc)

        self._result = result
        self._worker = threading.Thread(target=work, name="attnloop-flann-build", daemon=True)
        self._worker.start()
        if not background:
            self._worker.join()
        self._poll()

    def _poll(self) -> None:
        """Install a finished build (atomic swap) and surface its error, if any."""
        if self._worker is None or self._worker.is_alive():
            return
        self._worker = None
        out = self._result.pop() if self._result else None
        if isinstance(out, BaseException):
            raise RuntimeError("building the FLANN k-means tree failed") from out
        if out is not None and out.n > self.n_indexed:
            self._tree = out
            self.num_builds += 1

    def wait(self) -> None:
        """Block until a running background build has finished and is installed."""
        if self._worker is not None:
            self._worker.join()
        self._poll()

    def rebuild(self) -> None:
        """Build a tree over every stored row now (synchronously); no-op below ``min_tree_size`` or exact."""
        self.wait()
        if not self.config.exact and self._n >= self.config.min_tree_size and self.n_indexed < self._n:
            self._start_build(background=False)

    # ------------------------------------------------------------------ queries
    def _eligible(self, max_ids: np.ndarray | None, nq: int) -> np.ndarray:
        if max_ids is None:
            return np.full(nq, self._n, dtype=np.int64)
        return np.searchsorted(self._ids[: self._n], max_ids, side="right").astype(np.int64)

    def _prepare_queries(self, query, max_id):
        q, single = _to_numpy_2d(query, "query")
        if self._dim is not None and q.shape[1] != self._dim:
            raise ValueError(f"query has dimension {q.shape[1]} but the index holds dimension {self._dim} "
                             f"(got shape {tuple(q.shape)})")
        if self.config.normalize:
            q = _l2_normalize(q)
        if max_id is None:
            max_ids = None
        else:
            max_ids = _as_array(max_id, np.int64)
            if max_ids.ndim > 1 or (max_ids.ndim == 1 and max_ids.shape[0] not in (1, q.shape[0])):
                raise ValueError(f"max_id must be a scalar or have shape ({q.shape[0]},), "
                                 f"got {tuple(max_ids.shape)}")
            max_ids = np.broadcast_to(max_ids, (q.shape[0],))
        device = query.device if isinstance(query, Tensor) else torch.device("cpu")
        return q, single, max_ids, device

    def search(self, query, k: int = 10, max_id=None) -> tuple[Tensor, Tensor]:
        """The ``k`` most similar eligible keyframes of each query.

        Args:
            query: ``(D,)`` or ``(Q, D)`` descriptors (tensor on any device, or array).
            k: neighbours per query.
            max_id: only keyframes with ``id <= max_id`` are eligible (the temporal exclusion window:
                ``max_id = query_id - window``); a scalar or ``(Q,)``; ``None``: all keyframes.

        Returns:
            ids (long) and cosine similarities (float32), on the query's device, most similar first:
            ``(K,)`` each for a ``(D,)`` query, ``(Q, K)`` each for ``(Q, D)``, where
            ``K = min(k, most eligible keyframes of any query)``; rows of a batch with fewer eligible
            keyframes are padded with id ``-1`` and similarity ``-inf``. ``K = 0`` (empty tensors) when
            nothing is eligible.
        """
        if int(k) < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        q, single, max_ids, device = self._prepare_queries(query, max_id)
        self._poll()
        nq = q.shape[0]
        n_elig = self._eligible(max_ids, nq) if self._n else np.zeros(nq, dtype=np.int64)
        kk = int(min(k, n_elig.max(initial=0)))
        out_ids = np.full((nq, kk), -1, dtype=np.int64)
        out_sim = np.full((nq, kk), -np.inf, dtype=np.float32)
        if kk > 0:
            tree = None if self.config.exact else self._tree
            data = self._data
            for i in range(nq):
                m = int(n_elig[i])
                if m == 0:
                    continue
                rows = self._candidate_rows(q[i], m, kk, tree, data)
                sims = _matvec(data[rows], q[i])
                order = np.argsort(-sims, kind="stable")[:kk]
                out_ids[i, : order.size] = self._ids[rows[order]]
                out_sim[i, : order.size] = sims[order]
        ids_t = torch.from_numpy(out_ids).to(device)
        sim_t = torch.from_numpy(out_sim).to(device)
        return (ids_t[0], sim_t[0]) if single else (ids_t, sim_t)

    def _candidate_rows(
        self, q: np.ndarray, m: int, k: int, tree: _Tree | None, data: np.ndarray
    ) -> np.ndarray:
        """Rows (in ``[0, m)``) that contain the k nearest of the eligible prefix ``[0, m)``."""
        excess = 0 if tree is None else max(0, tree.n - m)
        # Brute force when there is no tree, or when the window cuts so deep into the tree that asking it
        # for k + excess neighbours would cost more than scanning the prefix.
        if tree is None or excess > max(4 * k, 64):
            return _topk_rows(_matvec(data[:m], q), k)
        kq = min(k + excess, tree.n)
        idx, _ = tree.flann.knnSearch(q[None], kq, params=dict(checks=int(self.config.checks)))
        idx = idx[0].astype(np.int64)
        parts = [idx[(idx >= 0) & (idx < min(m, tree.n))]]
        if m > tree.n:  # the exact tail
            parts.append(tree.n + _topk_rows(_matvec(data[tree.n: m], q), k))
        return np.unique(np.concatenate(parts))

    def similarities(self, query, max_id=None, max_samples: int | None = None) -> tuple[Tensor, Tensor]:
        """Exact similarities of one query to every eligible keyframe (or an even sample of them).

        Args:
            query: ``(D,)`` descriptor.
            max_id: only keyframes with ``id <= max_id`` (see :meth:`search`); ``None``: all.
            max_samples: at most this many eligible keyframes: every ``ceil(M / max_samples)``-th
                eligible row (deterministic, spread over the whole database); ``None``: all.

        Returns:
            ids ``(M,)`` (long) and similarities ``(M,)`` (float32) in id order, on the query's device.
        """
        q, single, max_ids, device = self._prepare_queries(query, max_id)
        if not single:
            raise ValueError(f"similarities takes one query of shape (D,), got {tuple(q.shape)}")
        m = int(self._eligible(max_ids, 1)[0]) if self._n else 0
        if m == 0:
            rows = np.zeros(0, dtype=np.int64)
            sims = np.zeros(0, dtype=np.float32)
        else:
            # Every step-th row: a strided view, scanned without copying (BLAS takes the row stride).
            step = 1 if max_samples is None or m <= max_samples else -(-m // int(max_samples))
            rows = np.arange(0, m, step)
            sims = _matvec(self._data[0:m:step], q[0])
        return (torch.from_numpy(self._ids[rows].copy()).to(device),
                torch.from_numpy(np.ascontiguousarray(sims, dtype=np.float32)).to(device))


def _topk_rows(sims: np.ndarray, k: int) -> np.ndarray:
    if sims.size <= k:
        return np.arange(sims.size)
    return np.argpartition(-sims, k - 1)[:k]


# ----------------------------------------------------------------------------------------------
# Loop-candidate detection
# ----------------------------------------------------------------------------------------------
@dataclass
class LoopCandidates:
    """The answer to one query keyframe.

    Attributes:
        ids: accepted candidate keyframe ids ``(M,)`` (long), most similar first.
        scores: their cosine similarities ``(M,)`` (float32).
        threshold: the query's adaptive threshold (``inf`` when too few keyframes were eligible).
        top_ids: the raw top-k neighbours ``(K,)`` before threshold and consistency (for evaluation).
        top_scores: their similarities ``(K,)``.
    """

    ids: Tensor
    scores: Tensor
    threshold: float
    top_ids: Tensor
    top_scores: Tensor

    def __len__(self) -> int:
        return int(self.ids.numel())


class LoopCandidateDetector:
    """Per-keyframe loop-candidate selection: index search, adaptive threshold, temporal consistency.

    The SLAM system calls :meth:`add_and_query` once per new keyframe; each call first queries the
    database of earlier keyframes (outside the exclusion window), then adds the new keyframe.

    Args:
        config: :class:`LoopDetectorConfig`.

    Example:
        >>> det = LoopCandidateDetector(LoopDetectorConfig(window=5))
        >>> gen = torch.Generator().manual_seed(0)
        >>> places = torch.randn(40, 64, generator=gen)
        >>> for i in range(40):
        ...     out = det.add_and_query(places[i] + 0.1 * torch.randn(64, generator=gen), keyframe_id=i)
        >>> out = det.add_and_query(places[3] + 0.1 * torch.randn(64, generator=gen), keyframe_id=40)
        >>> out.ids[:1].tolist(), out.scores.shape == out.ids.shape
        ([3], True)
        >>> det.similarities(40)[0].shape
        torch.Size([36])
    """

    def __init__(self, config: LoopDetectorConfig | None = None) -> None:
        self.config = config or LoopDetectorConfig()
        self.index = KeyframeIndex(self.config.index)
        # Threshold-passing ids of the previous queries (newest last), for temporal consistency.
        self._history: deque = deque(maxlen=max(self.config.consistency - 1, 0))

    def __len__(self) -> int:
        return len(self.index)

    def query(self, descriptor, keyframe_id: int) -> LoopCandidates:
        """Candidates for a query keyframe without adding it or updating the consistency history."""
        return self._query(descriptor, int(keyframe_id), update=False)

    def add_and_query(self, descriptor, keyframe_id: int, timestamp: float | None = None) -> LoopCandidates:
        """Query the database with a new keyframe, then add it.

        Args:
            descriptor: ``(D,)`` descriptor of the new keyframe (tensor on any device, or array).
            keyframe_id: its id, larger than every id added before.
            timestamp: optional, stored with it.

        Returns:
            :class:`LoopCandidates` (tensors on the descriptor's device).
        """
        kid = int(keyframe_id)
        if len(self.index) and kid <= int(self.index._ids[len(self.index) - 1]):
            raise ValueError(f"keyframe_id {kid} must be larger than the last added id "
                             f"{int(self.index._ids[len(self.index) - 1])}")
        out = self._query(descriptor, kid, update=True)
        self.index.add(descriptor, ids=[kid], timestamps=None if timestamp is None else [timestamp])
        return out

    def _query(self, descriptor, kid: int, update: bool) -> LoopCandidates:
        cfg = self.config
        if isinstance(descriptor, Tensor) and descriptor.dim() != 1 or (
                not isinstance(descriptor, Tensor) and np.ndim(descriptor) != 1):
            raise ValueError(f"descriptor must have shape (D,), got {tuple(np.shape(descriptor))}")
        device = descriptor.device if isinstance(descriptor, Tensor) else torch.device("cpu")
        max_id = kid - cfg.window
        top_ids, top_sims = self.index.search(descriptor, k=cfg.top_k, max_id=max_id)
        _, dist = self.index.similarities(descriptor, max_id=max_id, max_samples=cfg.threshold_samples)
        thr = float(adaptive_threshold(dist.cpu(), cfg.threshold))
        above = top_sims.cpu() > thr
        passed_ids = top_ids.cpu()[above]
        passed_sims = top_sims.cpu()[above]
        keep = torch.tensor([self._consistent(int(c)) for c in passed_ids], dtype=torch.bool)
        if update and self._history.maxlen:
            self._history.append(passed_ids.numpy().copy())
        return LoopCandidates(ids=passed_ids[keep].to(device), scores=passed_sims[keep].to(device),
                              threshold=thr, top_ids=top_ids, top_scores=top_sims)

    def _consistent(self, candidate: int) -> bool:
        need = self.config.consistency - 1
        if need == 0:
            return True
        streak = 0
        for prev in reversed(self._history):
            if prev.size and np.any(np.abs(prev - candidate) <= self.config.consistency_radius):
                streak += 1
            else:
                break
        return streak >= need

    def similarities(self, query_id: int, window: int | None = None) -> tuple[Tensor, Tensor]:
        """Exact similarities of a stored keyframe to every keyframe with ``id <= query_id - window``.

        For the loop-closure evaluation (precision/recall over all pairs).

        Args:
            query_id: id of a stored keyframe.
            window: exclusion window (default ``config.window``; ``1`` = all earlier keyframes).

        Returns:
            ids ``(M,)`` (long) and similarities ``(M,)`` (float32), in id order.
        """
        w = self.config.window if window is None else int(window)
        row = int(self.index.rows_of([query_id])[0])
        return self.index.similarities(self.index._data[row], max_id=int(query_id) - w)
