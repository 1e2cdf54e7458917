"""The keyframe database: stored descriptors, an approximate structure over them, exact re-scoring (docs/scale.md).

Ids increase with every ``add``, so the rows eligible under ``max_id`` are a prefix.
"""
from __future__ import annotations

import threading

import numpy as np
import torch

from attnloop.index.config import IndexConfig, config_from_dict, config_to_dict, resolve_backend
from attnloop.index.exact import check_count, scan_tolerance, topk_rows
from attnloop.index.persistence import IndexFileError, file_name, read_index_file, save_index
from attnloop.index.storage import GATHER_BYTES, KeyframeStore
from attnloop.index.structures import STRUCTURES

Tensor = torch.Tensor

__all__ = ["INDEX_FORMAT", "INDEX_FORMAT_VERSION", "KeyframeIndex"]

INDEX_FORMAT = "attnloop.KeyframeIndex"
INDEX_FORMAT_VERSION = 1
SUPPORTED_VERSIONS = (1,)  # format versions from_state reads
# Norm a stored row of a normalising index may have: 1 up to float16 rounding (or 0: a zero descriptor).
_UNIT_ROW_NORM = 1.01


def _to_numpy_2d(x, name: str) -> tuple[np.ndarray, bool]:
    """(N, D) or (D,) tensor/array -> contiguous float32 (N, D) numpy array, and whether it was 1-D."""
    arr = (x.detach().to(device="cpu", dtype=torch.float32).numpy() if isinstance(x, Tensor)
           else np.asarray(x, dtype=np.float32))
    if arr.ndim not in (1, 2):
        raise ValueError(f"{name} must have shape (D,) or (N, D), got {tuple(arr.shape)}")
    return np.ascontiguousarray(np.atleast_2d(arr)), arr.ndim == 1


def _as_array(x, dtype=None) -> np.ndarray:
    return np.asarray(x.detach().cpu().numpy() if isinstance(x, Tensor) else x, dtype=dtype)


def _as_int_array(x, name: str) -> np.ndarray:
    """``x`` (tensor, array, sequence or scalar) as int64; ValueError on a non-integral or out-of-range value."""
    arr = _as_array(x)
    if arr.dtype.kind == "f":
        bad = ~np.isfinite(arr) | (arr != np.round(arr)) | (np.abs(arr) >= 2.0 ** 63)
        if np.any(bad):
            raise ValueError(f"{name} must be integers, got {arr[bad].ravel()[:5].tolist()}")
    elif arr.dtype.kind == "u":
        if arr.size and arr.max() > np.iinfo(np.int64).max:
            raise ValueError(f"{name} must fit in int64, got {int(arr.max())}")
    elif arr.dtype.kind != "i":
        raise ValueError(f"{name} must be integers, got dtype {arr.dtype}")
    return arr.astype(np.int64)


def _record_int(meta: dict, key: str, minimum: int) -> int:
    value = meta[key]
    if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
        raise ValueError(f"the record's {key!r} must be an integer >= {minimum}, got {value!r}")
    return value


def _l2_normalize(x: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(x, axis=1, keepdims=True)
    return x / np.maximum(norm, 1e-12)  # a zero descriptor stays zero (similarity 0 to everything)


class KeyframeIndex:
    """Growing keyframe database with an exact scan, a FLANN tree or a faiss HNSW graph behind one interface.

    Not safe for concurrent ``add``/``search`` calls (its only concurrency is its own background build).

    Args:
        config: :class:`~attnloop.index.config.IndexConfig` (default: ``backend="auto"``).
        dim: descriptor size ``D``; inferred from the first ``add`` when ``None``.

    Raises:
        ImportError: ``backend="faiss"`` where faiss is not installed.
    """

    def __init__(self, config: IndexConfig | None = None, dim: int | None = None) -> None:
        self.config = config or IndexConfig()
        self.backend = resolve_backend(self.config.backend)  # "exact" | "flann" | "faiss"
        self._store = None if dim is None else KeyframeStore(dim, self.config.storage)
        self._structure = None
        self._worker: threading.Thread | None = None
        self._result: list = []  # the worker's (structure | exception), read by _poll
        self.num_builds = 0

    def __len__(self) -> int:
        return 0 if self._store is None else self._store.n

    @property
    def dim(self) -> int | None:
        """Descriptor size ``D`` (``None`` before the first add)."""
        return None if self._store is None else self._store.dim

    def use_config(self, config: IndexConfig) -> None:
        """Replace the settings read at query time (``checks``, ``ef_search``, ``exact_below``, ``rerank``)."""
        if not isinstance(config, IndexConfig):
            raise TypeError(f"config must be an IndexConfig, got {type(config).__name__}")
        self.config = config
        if self._structure is not None:
            self._structure.config = config

    @property
    def n_indexed(self) -> int:
        """Rows covered by the current structure (the rest is scanned exactly)."""
        s = self._structure
        return 0 if s is None else s.n

    @property
    def building(self) -> bool:
        """Whether a background build is running."""
        return self._worker is not None and self._worker.is_alive()

    @property
    def ids(self) -> Tensor:
        """Keyframe ids ``(N,)`` (long), in insertion (= increasing) order."""
        return torch.from_numpy(self._ids().copy())

    @property
    def last_id(self) -> int | None:
        """The largest (= last added) keyframe id, ``None`` when empty."""
        return int(self._store.ids[-1]) if len(self) else None

    @property
    def timestamps(self) -> Tensor:
        """Timestamps ``(N,)`` (float64; NaN where none was given)."""
        ts = np.zeros(0) if self._store is None else self._store.timestamps
        return torch.from_numpy(ts.copy())

    @property
    def descriptors(self) -> Tensor:
        """The stored (normalised) descriptors ``(N, D)``, a float32 copy."""
        if self._store is None:
            return torch.zeros(0, 0)
        return torch.from_numpy(self._store.view().astype(np.float32))

    def descriptors_of(self, ids) -> Tensor:
        """Stored descriptors ``(M, D)`` (float32) of keyframe ids ``(M,)``; ValueError naming an unknown id."""
        rows = self.rows_of(ids).numpy()  # names an unknown id, also in an empty index
        if self._store is None:
            return torch.zeros((0, self.dim or 0), dtype=torch.float32)
        return torch.from_numpy(self._store.rows(rows))

    def rows_of(self, ids) -> Tensor:
        """Buffer rows of the given keyframe ids ``(M,)``; ValueError naming an unknown id."""
        q = np.atleast_1d(_as_int_array(ids, "ids"))
        stored = self._ids()
        rows = np.searchsorted(stored, q)
        ok = rows < stored.size  # a binary search per id: O(log N), the index holds every keyframe of a run
        ok[ok] = stored[rows[ok]] == q[ok]
        if not np.all(ok):
            raise ValueError(f"unknown keyframe id(s) {q[~ok].tolist()[:5]} "
                             f"(the index holds {len(self)} keyframes)")
        return torch.from_numpy(rows)

    def _ids(self) -> np.ndarray:
        return np.zeros(0, dtype=np.int64) if self._store is None else self._store.ids

    def add(self, descriptors, ids=None, timestamps=None) -> None:
        """Append keyframes.

        Args:
            descriptors: ``(D,)`` or ``(M, D)`` tensor or array (any device; stored on the CPU in
                ``config.storage``).
            ids: ``(M,)`` integer keyframe ids (integral floats are accepted, others refused), strictly
                increasing and above every stored id; default continues from the last id (``0, 1, 2, ...``).
            timestamps: ``(M,)`` optional, stored for the caller.
        """
        x, _ = _to_numpy_2d(descriptors, "descriptors")
        m, d = x.shape
        if self._store is None:
            self._store = KeyframeStore(d, self.config.storage)
        elif d != self._store.dim:
            raise ValueError(f"descriptors have dimension {d} but the index holds dimension {self._store.dim} "
                             f"(got shape {tuple(x.shape)})")
        if m == 0:
            return
        if not np.all(np.isfinite(x)):
            raise ValueError("descriptors contain NaN or inf")
        last = self.last_id
        if ids is None:
            start = last + 1 if last is not None else 0
            new_ids = np.arange(start, start + m, dtype=np.int64)
        else:
            new_ids = np.atleast_1d(_as_int_array(ids, "ids"))
            if new_ids.shape != (m,):
                raise ValueError(f"ids must have shape ({m},), got {tuple(new_ids.shape)}")
        if np.any(np.diff(new_ids) <= 0) or (last is not None and new_ids[0] <= last):
            raise ValueError(f"keyframe ids must be strictly increasing; got {new_ids[:5].tolist()}... "
                             f"after last id {last}")
        ts = np.full(m, np.nan) if timestamps is None else np.atleast_1d(_as_array(timestamps, np.float64))
        if ts.shape != (m,):
            raise ValueError(f"timestamps must have shape ({m},), got {tuple(ts.shape)}")
        x = _l2_normalize(x)
        self._poll()
        self._store.append(x, new_ids, ts)
        self._extend()
        self._maybe_rebuild()

    def _extend(self) -> None:
        """Append the rows the installed structure lacks, where it can grow."""
        s = self._structure
        if s is not None and s.extendable and s.n < self._store.n:
            s.extend(self._store.view(s.n))

    def _maybe_rebuild(self) -> None:
        s, f = self._structure, self.config.flann
        if self.backend == "exact" or len(self) < self.config.exact_below or self.building:
            return
        if s is None or (s.stale() if s.extendable
                         else len(self) - s.n >= max(f.rebuild_every, f.rebuild_fraction * s.n)):
            self._start_build(background=self.config.background)

    def _start_build(self, background: bool) -> None:
        snapshot = self._store.view()  # rows never written again
        cls, config = STRUCTURES[self.backend], self.config
        result: list = []

        def work() -> None:
            try:
                result.append(cls.build(snapshot, config))
            except BaseException as exc:  # surfaced in the caller's thread by _poll
                result.append(exc)

        self._result = result
        self._worker = threading.Thread(target=work, name=f"attnloop-{self.backend}-build", daemon=True)
        self._worker.start()
        if not background:
            self._worker.join()
        self._poll()

    def _poll(self) -> None:
        """Install a finished build (atomic swap), extend it to every row, and surface its error, if any."""
        if self._worker is None or self._worker.is_alive():
            return
        self._worker = None
        out = self._result.pop()  # the worker leaves its structure or its exception
        if isinstance(out, BaseException):
            raise RuntimeError(f"building the {self.backend} index structure failed") from out
        self._structure = out
        self.num_builds += 1
        self._extend()

    def wait(self) -> None:
        """Block until a running background build has finished and is installed."""
        if self._worker is not None:
            self._worker.join()
        self._poll()

    def rebuild(self) -> None:
        """Build a structure over every stored row now (synchronously), refitting its code, where one is due."""
        self.wait()
        if self.backend == "exact" or len(self) < self.config.exact_below:
            return
        if self.backend == "flann" and self.n_indexed == len(self):
            return
        self._start_build(background=False)

    def _eligible(self, max_ids: np.ndarray | None, nq: int) -> np.ndarray:
        if max_ids is None:
            return np.full(nq, len(self), dtype=np.int64)
        return np.searchsorted(self._ids(), max_ids, side="right").astype(np.int64)

    def _prepare_queries(self, query, max_id):
        q, single = _to_numpy_2d(query, "query")
        if self.dim is not None and q.shape[1] != self.dim:
            raise ValueError(f"query has dimension {q.shape[1]} but the index holds dimension {self.dim} "
                             f"(got shape {tuple(q.shape)})")
        bad = ~np.isfinite(q).all(axis=1)
        if bad.any():
            where = "the query contains" if single else f"query rows {np.flatnonzero(bad)[:10].tolist()} contain"
            raise ValueError(f"{where} NaN or inf (as float32)")
        q = _l2_normalize(q)
        if max_id is None:
            max_ids = None
        else:
            max_ids = _as_int_array(max_id, "max_id")
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
            ids (long) and cosine similarities (float32), on the query's device, most similar first, ties by
            id: ``(K,)`` each for a ``(D,)`` query, ``(Q, K)`` for ``(Q, D)``, ``K = min(k, most eligible
            keyframes of any query)``; shorter rows padded with id ``-1`` and similarity ``-inf``.

        Raises:
            ValueError: a query with NaN or inf (naming the rows), a wrong dimension, ``k < 1``, a
                non-integral ``max_id``.
        """
        k = check_count(k, "k", 1)
        q, single, max_ids, device = self._prepare_queries(query, max_id)
        self._poll()
        nq = q.shape[0]
        n_elig = self._eligible(max_ids, nq)
        kk = int(min(k, n_elig.max(initial=0)))
        out_ids = np.full((nq, kk), -1, dtype=np.int64)
        out_sim = np.full((nq, kk), -np.inf, dtype=np.float32)
        if kk > 0:
            structure, ids = self._structure, self._store.ids
            for i in range(nq):
                m = int(n_elig[i])
                if m == 0:
                    continue
                rows, sims = self._top(q[i], m, kk, structure)
                out_ids[i, : rows.size] = ids[rows]
                out_sim[i, : rows.size] = sims
        ids_t = torch.from_numpy(out_ids).to(device)
        sim_t = torch.from_numpy(out_sim).to(device)
        return (ids_t[0], sim_t[0]) if single else (ids_t, sim_t)

    # Re-scored in float64: a similarity must not depend on which other rows were re-scored with it, and ties
    # go to the lower row whichever path found the rows.
    def _top(self, q: np.ndarray, m: int, k: int, structure) -> tuple[np.ndarray, np.ndarray]:
        """Rows and similarities of the ``k`` best of the eligible prefix ``[0, m)``, best first, ties by row."""
        q64 = q.astype(np.float64)
        # how far below the k-th value of a float32 scan a row of the exact top k can score
        tol = scan_tolerance(self._store.dim, float(np.linalg.norm(q64)), _UNIT_ROW_NORM)
        if structure is None or m < self.config.exact_below:
            return self._scan(q, q64, 0, m, k, tol)
        prop = structure.candidates(q, k * self.config.rerank, m)
        if prop is None:  # a window so deep that a scan is cheaper
            return self._scan(q, q64, 0, m, k, tol)
        prop = np.unique(prop)
        p_sims = self._rescore(prop, q64)
        rows, sims = prop, p_sims
        if m > structure.n:  # the exact tail (its rows all follow the structure's)
            t_rows, t_sims = self._scan(q, q64, structure.n, m, k, tol)
            rows, sims = np.concatenate([prop, t_rows]), np.concatenate([p_sims, t_sims])
        order = np.argsort(-sims, kind="stable")[:k]
        rows, sims = rows[order], sims[order]
        # duplicate frames: the proposals may end inside a group of equal rows whose lower ids were left out
        if (sims.size == k and prop.size >= 2 and p_sims.min() >= sims[-1]
                and np.count_nonzero(p_sims == sims[-1]) >= 2):
            return self._scan(q, q64, 0, m, k, tol)
        return rows, sims

    def _scan(self, q, q64, start: int, stop: int, k: int, tol: float) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` best of rows ``[start, stop)``: every row a float32 scan cannot rule out, re-scored exactly (a
        chunk at a time), ties by row."""
        rows = start + topk_rows(self._store.matvec(q, start, stop), k, tol)
        chunk = GATHER_BYTES // (8 * max(1, self._store.dim)) + 1
        best_r, best_s = rows[:0], np.zeros(0, dtype=np.float32)
        for lo in range(0, rows.size, chunk):
            r = np.concatenate([best_r, rows[lo: lo + chunk]])  # the kept rows all precede this chunk's
            s = np.concatenate([best_s, self._rescore(rows[lo: lo + chunk], q64)])
            order = np.argsort(-s, kind="stable")[:k]
            best_r, best_s = r[order], s[order]
        return best_r, best_s

    def _rescore(self, rows: np.ndarray, q64: np.ndarray) -> np.ndarray:
        return (self._store.rows(rows, np.float64) @ q64).astype(np.float32)

    def similarities(self, query, max_id=None, max_samples: int | None = None) -> tuple[Tensor, Tensor]:
        """Exact similarities of one query to every eligible keyframe (or an even sample of them).

        Args:
            query: ``(D,)`` descriptor.
            max_id: only keyframes with ``id <= max_id`` (see :meth:`search`); ``None``: all.
            max_samples: when more keyframes are eligible, exactly this many of them, evenly spread from the
                first eligible row to the last; ``None``: all.

        Returns:
            ids ``(M,)`` (long) and similarities ``(M,)`` (float32) in id order, on the query's device.
        """
        if max_samples is not None:
            max_samples = check_count(max_samples, "max_samples", 1)
        q, single, max_ids, device = self._prepare_queries(query, max_id)
        if not single:
            raise ValueError(f"similarities takes one query of shape (D,), got {tuple(q.shape)}")
        m = int(self._eligible(max_ids, 1)[0])
        if m == 0:
            rows = np.zeros(0, dtype=np.int64)
            sims = np.zeros(0, dtype=np.float32)
        elif max_samples is None or m <= max_samples:
            rows = np.arange(m)
            sims = self._store.matvec(q[0], 0, m)
        else:  # spacing (m - 1) / (max_samples - 1) > 1: the rounded rows are distinct
            rows = np.floor(np.linspace(0, m - 1, max_samples) + 0.5).astype(np.int64)
            sims = self._store.matvec_rows(q[0], rows)
        return (torch.from_numpy(self._ids()[rows].copy()).to(device),
                torch.from_numpy(np.ascontiguousarray(sims, dtype=np.float32)).to(device))

    def state_dict(self) -> dict:
        """Everything needed to rebuild this index with identical answers.

        Returns:
            ``{"meta": dict, name: np.ndarray, ...}`` as :mod:`attnloop.index.persistence` describes; a build
            still running is not waited for.
        """
        self._poll()
        n, dim = len(self), self.dim
        meta = {"format": INDEX_FORMAT, "version": INDEX_FORMAT_VERSION, "config": config_to_dict(self.config),
                "backend": self.backend, "dim": dim, "n": n, "num_builds": self.num_builds, "structure": None}
        arrays = {
            "descriptors": (self._store.view().copy() if n else np.zeros((0, dim or 0), np.float32)),
            "ids": self._ids().copy(),
            "timestamps": (self._store.timestamps.copy() if n else np.zeros(0)),
        }
        if self._structure is not None:
            smeta, sarrays = self._structure.state()
            meta["structure"] = smeta
            arrays.update({f"structure.{k}": v for k, v in sarrays.items()})
        return {"meta": meta, **arrays}

    @classmethod
    def from_state(cls, state: dict, config: IndexConfig | None = None) -> KeyframeIndex:
        """The index a :meth:`state_dict` describes.

        Args:
            state: from :meth:`state_dict` (or :func:`attnloop.index.load_index`'s reading of a file).
            config: ``None`` (or the saved config): the saved structure as it was (identical answers); another
                config: the rows re-added under it. A saved ``"auto"`` structure this machine cannot load is
                rebuilt with the backend ``"auto"`` picks here.

        Raises:
            ValueError: a malformed state (format version, record entries, arrays, rows not unit length, a
                corrupt structure), naming what is wrong.
            ImportError: a saved faiss graph restored where faiss is not installed.
        """
        meta = state.get("meta") if isinstance(state, dict) else None
        if not isinstance(meta, dict) or meta.get("format") != INDEX_FORMAT:
            raise ValueError(f"not a keyframe index state (its 'meta' record lacks format {INDEX_FORMAT!r})")
        version = meta.get("version")
        supported = ", ".join(map(str, SUPPORTED_VERSIONS))
        if "version" not in meta:
            raise ValueError(f"the record has no format version (this library reads version {supported})")
        if type(version) is not int or version not in SUPPORTED_VERSIONS:
            raise ValueError(f"keyframe index format version {version!r} is not supported (this library reads "
                             f"version {supported})")
        for key in ("config", "dim", "n", "num_builds", "structure"):
            if key not in meta:
                raise ValueError(f"keyframe index record lacks {key!r}")
        for key in ("descriptors", "ids", "timestamps"):
            if key not in state:
                raise ValueError(f"keyframe index state lacks the array {key!r}")
        if not isinstance(meta["config"], dict):
            raise ValueError(f"the record's 'config' must be a dict, got {type(meta['config']).__name__}")
        try:
            saved = config_from_dict(meta["config"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"the record's config is invalid: {exc}") from exc
        n, num_builds = _record_int(meta, "n", 0), _record_int(meta, "num_builds", 0)
        dim = None if meta["dim"] is None and n == 0 else _record_int(meta, "dim", 1)
        desc = np.asarray(state["descriptors"])
        if desc.dtype.kind != "f":
            raise ValueError(f"descriptors have dtype {desc.dtype}, need floating point")
        ids = _as_int_array(state["ids"], "ids")
        try:
            ts = np.asarray(state["timestamps"], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"timestamps must be numbers ({exc})") from exc
        if desc.ndim != 2 or desc.shape[0] != n or (n and desc.shape[1] != dim):
            raise ValueError(f"descriptors have shape {tuple(desc.shape)}, the record says ({n}, {dim})")
        if ids.shape != (n,) or ts.shape != (n,):
            raise ValueError(f"ids {tuple(ids.shape)} and timestamps {tuple(ts.shape)} must have shape ({n},)")
        if n and np.any(np.diff(ids) <= 0):
            raise ValueError("keyframe ids must be strictly increasing")
        if n and not np.all(np.isfinite(desc)):
            raise ValueError("descriptors contain NaN or inf")
        smeta = meta["structure"]
        if smeta is not None:
            if not isinstance(smeta, dict) or smeta.get("kind") not in STRUCTURES:
                kind = smeta.get("kind") if isinstance(smeta, dict) else smeta
                raise ValueError(f"the record's structure must be one of the kinds {sorted(STRUCTURES)}, "
                                 f"got {kind!r}")
            if "n" not in smeta:
                raise ValueError("the record's structure lacks 'n' (the rows it covers)")
            s_n = smeta["n"]
            if not isinstance(s_n, int) or isinstance(s_n, bool) or not 1 <= s_n <= n:
                raise ValueError(f"the saved structure covers {s_n!r} rows, need an integer in [1, {n}]")
        use = config or saved
        if config is not None and config != saved:
            out = cls(config)
            if n:
                out.add(desc, ids=ids, timestamps=ts)
            return out
        out = cls(use, dim=dim)
        backend = out.backend
        if n:
            out._store.append(desc.astype(out._store.dtype, copy=False), ids, ts)
            norms = out._store.row_norms()
            bad = (norms != 0) & (np.abs(norms - 1) > _UNIT_ROW_NORM - 1)
            if np.any(bad):
                raise ValueError(f"descriptor rows {np.flatnonzero(bad)[:5].tolist()} have norms "
                                 f"{np.round(norms[bad][:5], 4).tolist()}: descriptors are L2-normalised, so "
                                 "every stored row must have norm 1 (or 0)")
        if smeta is not None and smeta["kind"] == backend:
            sarrays = {k[len("structure."):]: v for k, v in state.items() if k.startswith("structure.")}
            try:
                out._structure = STRUCTURES[backend].from_state(smeta, sarrays, out._store.view(), use)
                out._extend()
            except (ValueError, ImportError, MemoryError):
                raise
            except Exception as exc:  # OpenCV's and faiss's errors on a corrupt blob
                first = (str(exc).strip().splitlines() or [""])[0][:200]
                raise ValueError(f"the saved {backend} structure is corrupt ({type(exc).__name__}: {first})") from exc
            out.num_builds = num_builds
        elif n:
            out._maybe_rebuild()  # a structure of another kind (or none): built here as adds would
        return out

    def save(self, file) -> None:
        """Write :meth:`state_dict` to one ``.npz`` file (a path or a binary file object; no pickles)."""
        save_index(self, file)

    @classmethod
    def load(cls, file, config: IndexConfig | None = None) -> KeyframeIndex:
        """Read an index written by :meth:`save` (a path or a binary file object).

        Args:
            file: a path or a binary file object.
            config: ``None`` to restore the saved index as it was; another config rebuilds the structure
                (see :meth:`from_state`).

        Raises:
            FileNotFoundError: no such file.
            IndexFileError: not a keyframe-index file, an unsupported format version, or inconsistent or
                corrupt contents, naming the file and what is wrong.
            ImportError: the file holds a faiss graph and faiss is not installed here.
        """
        state = read_index_file(file)
        try:
            return cls.from_state(state, config)
        except (ValueError, TypeError, KeyError, IndexError, AttributeError, OverflowError) as exc:
            raise IndexFileError(f"{file_name(file)}: {exc}") from exc


def load_index(file, config: IndexConfig | None = None) -> KeyframeIndex:
    """Read an index written by :func:`~attnloop.index.save_index` (:meth:`KeyframeIndex.load`)."""
    return KeyframeIndex.load(file, config)
