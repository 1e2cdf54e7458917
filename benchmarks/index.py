"""Keyframe index at scale: every backend side by side, from 10^4 to 10^6 keyframes (attnloop.index).

For each descriptor set and size, every variant (a backend with its settings) is built over the same rows
and answers the same queries: recall@10 against the exact top-10 (of the rows as stored), "top-1 found"
(the exact nearest neighbour is among the 10 returned), milliseconds per query (one query at a time, as
SLAM asks), build time (adding every row, then one build over all of them) and memory (growth of the
process's resident set while the index is built: stored descriptors + structure). Query timings of the
variants kept in memory together are interleaved (round r of every variant, then round r + 1, ...) and
the median round is reported, so that a change of machine load hits them all alike; at 10^6 the variants
are built and measured one after the other (memory) and the exact scan answers fewer queries.

A *stream* table then measures the SLAM use on the built index: one keyframe at a time, search with an
exclusion window of 30 ids, then add (graph insertion, or the FLANN tail), with recall against the exact
answer over the eligible rows.

Data (benchmarks/index_data.py): "clustered" (N/20 isotropic places x ~20 views, noise norm 1.0: cosine
0.5 within a place), "hard" (noise 1.5: cosine 0.31), "real" (the same structure with the mean,
covariance and view-to-view changes of real descriptors: redkitchen + rtabmap-samples); "random"
(i.i.d. directions, the worst case). ``--real-sets`` measures every variant on the real descriptors
themselves (structures forced on: ``exact_below=32``): recall@10 per query keyframe against all earlier
ones outside the window, and whether the loop detector accepts the same candidates as with the exact scan.
``--crossover`` times the exact scan against the default structure from 1k to 16k keyframes (where
``exact_below`` belongs).

Usage:
    python -m benchmarks.index                                   # 1e4 and 1e5; clustered, real; all variants
    python -m benchmarks.index --sizes 1000000 --data clustered real --variants exact faiss-pca128 \\
        --storage float16 --exact-queries 20 --build-threads 2 --stream 50  # the 10^6 run
    python -m benchmarks.index --diagnose --sizes 1000000 --data clustered real --storage float16  # code vs graph
    python -m benchmarks.index --diagnose --sizes 200000 --data clustered --graphs 32:80 64:80 --ef-sweep 64 128 256 512
    python -m benchmarks.index --real-sets --skip-synthetic
    python -m benchmarks.index --crossover --skip-synthetic

Prints markdown tables.
"""
from __future__ import annotations

import argparse
import ctypes
import gc
import os
import platform
import resource
import time
from dataclasses import replace

import numpy as np
import torch

from attnloop.index import (
    FaissConfig,
    FlannConfig,
    IndexConfig,
    KeyframeIndex,
    LoopCandidateDetector,
    LoopDetectorConfig,
    faiss_available,
    fit_pca,
)
from benchmarks.index_data import Clustered, RealStatistics, exact_reference, real_descriptors

DEFAULT = IndexConfig()
# name -> (IndexConfig settings, the query-time knob and its swept values)
VARIANTS = {
    "exact": ({"backend": "exact"}, None),
    "flann": ({"backend": "flann", "reduce_dim": None}, ("checks", [128, 512, 2048])),
    "flann-pca128": ({"backend": "flann", "reduce_dim": 128}, ("checks", [128, 512, 2048])),
    "faiss": ({"backend": "faiss", "reduce_dim": None}, ("ef_search", [32, 64, 128])),
    "faiss-pca128": ({"backend": "faiss", "reduce_dim": 128}, ("ef_search", [32, 64, 128])),
    "faiss-pca256": ({"backend": "faiss", "reduce_dim": 256}, ("ef_search", [32, 64, 128])),
    # half the default's links: what loses recall at 10^6 keyframes
    "faiss-pca128-m32": ({"backend": "faiss", "reduce_dim": 128, "faiss": FaissConfig(m=32)},
                         ("ef_search", [64, 128])),
    # the choices behind the defaults (--real-sets): fewer candidates, faiss's default ef_construction
    "faiss-pca128-rerank4": ({"backend": "faiss", "reduce_dim": 128, "rerank": 4}, ("ef_search", [64])),
    "faiss-efc40": ({"backend": "faiss", "reduce_dim": None, "faiss": FaissConfig(ef_construction=40)},
                    ("ef_search", [64])),
}
SYNTHETIC_VARIANTS = ["exact", "flann", "flann-pca128", "faiss", "faiss-pca128",
                      "faiss-pca256"]
SPREAD = {"clustered": 1.0, "hard": 1.5}


def rss_mb() -> float:
    """Resident set size of this process now (MB)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def is_default(name: str) -> bool:
    """Whether a variant is what ``IndexConfig()`` builds here (backend "auto")."""
    settings, _ = VARIANTS[name]
    cfg = IndexConfig(**settings)
    return cfg.backend == KeyframeIndex().backend and replace(cfg, backend=DEFAULT.backend) == DEFAULT


def variant_config(name: str, n: int, storage: str) -> IndexConfig:
    settings, _ = VARIANTS[name]
    # exact_below = n: no structure until every row is in, then one build over all of them (the build time).
    return IndexConfig(**settings, storage=storage, exact_below=max(n, 1), background=False)


def set_knob(index: KeyframeIndex, name: str, value) -> None:
    # The structures read these at query time.
    if name == "checks":
        index.use_config(replace(index.config, flann=replace(index.config.flann, checks=value)))
    elif name == "ef_search":
        index.use_config(replace(index.config, faiss=replace(index.config.faiss, ef_search=value)))


def make_data(kind: str, n: int, dim: int, real: dict | None):
    if kind in SPREAD:
        return Clustered(n, dim, spread=SPREAD[kind])
    if kind == "random":
        return Clustered(n, dim, spread=0.0, views=1)  # every row its own random "place": i.i.d. directions
    if kind == "real":
        return RealStatistics(n, torch.cat([real["kitchen"], real["rtabmap"]]), real["kitchen"])
    raise ValueError(kind)


def _release() -> None:
    """Collect garbage and hand freed heap pages back (so that resident-memory deltas measure live data)."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except OSError:  # not glibc
        pass


def build(name: str, data, storage: str):
    """Add every row (timed: the adds and the one build, not the data generation); -> index, s, MB."""
    _release()
    rss0 = rss_mb()
    index = KeyframeIndex(variant_config(name, data.n, storage))
    elapsed = 0.0
    for _, rows in data.chunks():
        t0 = time.perf_counter()
        index.add(rows)
        elapsed += time.perf_counter() - t0
        del rows  # not resident when the memory is read
    _release()
    return index, elapsed, rss_mb() - rss0


def recall(sims: list, ref_sims: np.ndarray, tol: float = 1e-5) -> tuple[float, float]:
    """Tie-aware recall@k and top-1 found from the returned similarities (exact re-scores of the rows).

    A returned keyframe counts as one of the true top-k when its similarity reaches the k-th exact one
    (within float32 rounding): duplicate frames (identical descriptors) make "the" top-k ambiguous.

    Args:
        sims: per query, the similarities ``(<= k,)`` the index returned.
        ref_sims: ``(Q, k)`` the exact top-k similarities, most similar first.
    """
    k = ref_sims.shape[1]
    r = np.mean([min(k, int(np.sum(s >= ref[-1] - tol))) / k for s, ref in zip(sims, ref_sims)])
    top1 = np.mean([s.size > 0 and s.max() >= ref[0] - tol for s, ref in zip(sims, ref_sims)])
    return float(r), float(top1)


def measure(indexes: dict, queries: np.ndarray, ref: np.ndarray, k: int, rounds: int, exact_queries: int,
            knobs: dict | None = None):
    """Interleaved timing rounds over every (variant, knob value).

    Args:
        indexes: name -> built index.
        knobs: name -> (knob, values) (default: the variant's sweep in VARIANTS).

    Returns:
        {(name, knob, value): (median ms per query, recall@k, top-1 found, queries answered)}.
    """
    knobs = knobs if knobs is not None else {name: VARIANTS[name][1] for name in indexes}
    qt = torch.from_numpy(queries)
    slots = [(name, kn[0] if kn else None, value)
             for name, kn in knobs.items() for value in (kn[1] if kn else [None])]
    nq = queries.shape[0]
    per_round = {s: [] for s in slots}
    answers = {s: [None] * nq for s in slots}
    bounds = np.linspace(0, nq, rounds + 1).astype(int)
    for r in range(rounds):
        for slot in slots:
            name, knob, value = slot
            index = indexes[name]
            set_knob(index, knob, value)
            lo, hi = bounds[r], bounds[r + 1]
            if index.backend == "exact":  # the scan is slow at 10^6: a share of the queries
                hi = min(hi, lo + max(1, -(-exact_queries // rounds)))
            index.search(qt[lo], k=k)  # warm-up
            t0 = time.perf_counter()
            for i in range(lo, hi):
                answers[slot][i] = index.search(qt[i], k=k)[1].numpy()
            per_round[slot].append(1e3 * (time.perf_counter() - t0) / (hi - lo))
    out = {}
    for slot in slots:
        got = [(a, b) for a, b in zip(answers[slot], ref) if a is not None]
        rec, top1 = recall([a for a, _ in got], np.stack([b for _, b in got]))
        out[slot] = (float(np.median(per_round[slot])), rec, top1, len(got))
    for name, index in indexes.items():  # back to the defaults
        set_knob(index, "checks", DEFAULT.flann.checks)
        set_knob(index, "ef_search", DEFAULT.faiss.ef_search)
    return out


def stream(index: KeyframeIndex, data, n_stream: int, k: int, window: int) -> str:
    """The SLAM use on a built index: search (window) then add, one new keyframe at a time."""
    index.use_config(replace(index.config, exact_below=DEFAULT.exact_below))  # as a SLAM run (the bulk build used n)
    n0 = len(index)
    new = data.queries(n_stream, seed=777)  # new views of stored places: revisits
    builds0 = index.num_builds
    t_search, t_add, answers = np.zeros(n_stream), np.zeros(n_stream), []
    for i in range(n_stream):
        kid = n0 + i
        t0 = time.perf_counter()
        _, sims = index.search(new[i], k=k, max_id=kid - window)
        t1 = time.perf_counter()
        index.add(new[i], ids=[kid])
        t_add[i] = time.perf_counter() - t1
        t_search[i] = t1 - t0
        answers.append(sims.numpy())
    index.wait()
    # Exact answers over the eligible rows (base rows + stream rows before the window).
    ref = [torch.topk(index.similarities(new[i], max_id=n0 + i - window)[1], k).values.numpy()
           for i in range(n_stream)]
    rec, top1 = recall(answers, np.stack(ref))
    return (f"| {n0} | {n_stream} | {1e3 * np.median(t_search):.3f} | {1e3 * np.percentile(t_search, 99):.2f} "
            f"| {1e3 * np.median(t_add):.3f} | {1e3 * np.percentile(t_add, 99):.2f} | {rec:.3f} | {top1:.3f} "
            f"| {index.num_builds - builds0} |")


def synthetic(args, real: dict | None) -> None:
    wanted = args.variants or SYNTHETIC_VARIANTS
    names = [v for v in wanted if v == "exact" or VARIANTS[v][0]["backend"] != "faiss" or faiss_available()]
    if len(names) < len(wanted):
        print(f"(faiss not installed: skipped {sorted(set(wanted) - set(names))})\n")
    for kind in args.data:
        for n in args.sizes:
            data = make_data(kind, n, args.dim, real)
            queries = data.queries(args.queries)
            t0 = time.perf_counter()
            _, ref = exact_reference(data, queries, args.k, args.storage)
            print(f"\n### {kind}, {n} keyframes (D = {args.dim}, storage {args.storage}; exact reference "
                  f"{time.perf_counter() - t0:.1f} s; load average {os.getloadavg()[0]:.1f})\n", flush=True)
            keep = n <= args.keep_below
            built, rows = {}, []
            streams = []
            for name in names:
                index, t_build, mem = build(name, data, args.storage)
                built[name] = (t_build, mem)
                print(f"<!-- built {name}: {t_build:.1f} s, {mem:.0f} MB, load {os.getloadavg()[0]:.1f} -->",
                      flush=True)
                if keep:
                    rows.append((name, index))
                    continue
                res = measure({name: index}, queries, ref, args.k, args.rounds, args.exact_queries)
                _print_rows(kind, n, {name: built[name]}, res)
                if name in args.stream_variants and args.stream:
                    streams.append((name, stream(index, data, args.stream, args.k, 30)))
                del index
                _release()
            if keep:
                indexes = dict(rows)
                res = measure(indexes, queries, ref, args.k, args.rounds, args.exact_queries)
                _print_rows(kind, n, built, res, header=True)
                for name, index in rows:
                    if name in args.stream_variants and args.stream:
                        streams.append((name, stream(index, data, args.stream, args.k, 30)))
                del indexes, rows, index
                _release()
            if streams:
                print(f"\nStream on the built index ({kind}, {n}): one new keyframe at a time, search "
                      f"(k = {args.k}, window 30 ids) then add; medians and p99 in ms.\n")
                print("| variant | keyframes before | stream | search ms | p99 | add ms | p99 | recall@10 "
                      "| top-1 found | builds during |")
                print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
                for name, row in streams:
                    print(f"| {name} {row}")
    print(f"\npeak resident memory of the run: {peak_rss_mb():.0f} MB; load average at the end "
          f"{os.getloadavg()[0]:.1f}")


_HEADER_DONE = set()


def _print_rows(kind, n, built, res, header=True) -> None:
    if (kind, n) not in _HEADER_DONE:
        print("| variant | build s | index MB | knob | query ms | recall@10 | top-1 found | queries |")
        print("|---|---:|---:|---|---:|---:|---:|---:|")
        _HEADER_DONE.add((kind, n))
    for (name, knob, value), (ms, rec, top1, nq) in res.items():
        if name not in built:
            continue
        t_build, mem = built[name]
        default_knob = knob is None or value == getattr(DEFAULT.flann if knob == "checks" else DEFAULT.faiss, knob)
        mark = " **(default)**" if is_default(name) and default_knob else ""
        knob_s = "-" if knob is None else f"{knob} {value}"
        print(f"| {name}{mark} | {t_build:.1f} | {mem:.0f} | {knob_s} | {ms:.3f} | {rec:.3f} | {top1:.3f} | {nq} |",
              flush=True)


# ----------------------------------------------------------------------------------------------
def real_sets(args, real: dict) -> None:
    """Every variant on the real descriptors (structures forced on): recall@10 and detector agreement."""
    print("\n### Real descriptors (EfficientNet-Lite0 + DAM), structures forced on (exact_below = 32)\n")
    print("Each keyframe in order queries every earlier keyframe outside the window (kitchen: 30 frames; "
          "rtabmap-samples: 1 image), then is added. *kitchen, then rtabmap*: the 1000 kitchen frames are "
          "added first (not queried), then the corridor images query and are added: a code fitted on one "
          "place meeting another (84 rows: too few for the drift refit). recall@10 against the exact top-10 "
          "of the same query; *detector agrees*: the loop detector (LoopDetectorConfig defaults but the "
          "window) accepts exactly the candidates it accepts with the exact scan.\n")
    print("| set | keyframes | variant | recall@10 | top-1 found | detector agrees |")
    print("|---|---:|---|---:|---:|---:|")
    kitchen, rtab = real["kitchen"].float(), real["rtabmap"].float()
    sets = (("kitchen", kitchen, 30, 0), ("rtabmap", rtab, 1, 0),
            ("kitchen, then rtabmap", torch.cat([kitchen, rtab]), 1, kitchen.shape[0]))
    for set_name, desc, window, first_query in sets:
        ref_out = _detector_run(desc, "exact", window, first_query)
        for name in args.variants or list(VARIANTS):
            settings, _ = VARIANTS[name]
            if settings["backend"] == "faiss" and not faiss_available():
                continue
            index = KeyframeIndex(IndexConfig(**settings, exact_below=32, background=False))
            res, ref = [], []
            for i in range(desc.shape[0]):
                if i >= first_query and i - window + 1 >= args.k:  # queries with k eligible keyframes
                    res.append(index.search(desc[i], k=args.k, max_id=i - window)[1].numpy())
                    exact = index.similarities(desc[i], max_id=i - window)[1]
                    ref.append(torch.topk(exact, args.k).values.numpy())
                index.add(desc[i], ids=[i])
            rec, top1 = recall(res, np.stack(ref))
            out = _detector_run(desc, name, window, first_query)
            agree = np.mean([a == b for a, b in zip(out, ref_out)])
            print(f"| {set_name} | {desc.shape[0]} | {name} | {rec:.3f} | {top1:.3f} | {agree:.3f} |", flush=True)


def _detector_run(desc: torch.Tensor, name: str, window: int, first_query: int) -> list:
    settings, _ = VARIANTS[name]
    det = LoopCandidateDetector(LoopDetectorConfig(
        window=window, index=IndexConfig(**settings, exact_below=32, background=False)))
    det.index.add(desc[:first_query], ids=torch.arange(first_query))
    return [tuple(det.add_and_query(desc[i], keyframe_id=i).ids.tolist()) for i in range(first_query, desc.shape[0])]


def diagnose(args, real: dict | None) -> None:
    """Where the default's recall goes: the PCA code or the HNSW graph on it .

    For each descriptor set and size: the code of ``IndexConfig.reduce_dim`` (fitted as the index fits it)
    searched *exactly* over every row, its top ``R`` re-scored with the stored descriptors (the code's
    loss, for the default ``R = rerank * k`` and wider); then, for each ``--graphs M:ef_construction``, the
    HNSW graph on that same code answering through the index (the graph's loss: recall@10 after
    re-scoring, and the share of the code's exact top ``rerank * k`` that the graph proposes) over an
    ``ef_search`` sweep. Both on the first ``--diagnose-queries`` queries.
    """
    nq, k, r_default = args.diagnose_queries, args.k, DEFAULT.rerank * args.k
    widths = sorted({r_default, 2 * r_default, 4 * r_default, 8 * r_default})
    for kind in args.data:
        for n in args.sizes:
            data = make_data(kind, n, args.dim, real)
            queries = data.queries(args.queries)[:nq]
            _, ref = exact_reference(data, queries, k, args.storage)
            print(f"\n### Diagnosis: {kind}, {n} keyframes (D = {args.dim}, storage {args.storage}, {nq} queries, "
                  f"code {DEFAULT.reduce_dim}-d; load average {os.getloadavg()[0]:.1f})\n", flush=True)
            store = KeyframeIndex(IndexConfig(backend="exact", storage=args.storage))
            for _, rows in data.chunks():
                store.add(rows)
            x = store._store.view()
            code = fit_pca(x, DEFAULT.reduce_dim, seed=DEFAULT.seed)
            top = _code_topr(code, x, queries, max(widths))
            print("| candidates from | R | recall@10 after re-scoring |\n|---|---:|---:|")
            for r in widths:
                sims = [_rescore(store, q, rows[:r]) for q, rows in zip(queries, top)]
                print(f"| exact search on the code | {r} | {recall(sims, ref)[0]:.3f} |", flush=True)
            del x
            for spec in args.graphs:
                m, efc = (int(v) for v in spec.split(":"))
                cfg = IndexConfig(backend="faiss", storage=args.storage, exact_below=n, background=False,
                                  faiss=FaissConfig(m=m, ef_construction=efc))
                t0, c0 = time.perf_counter(), time.process_time()
                index = KeyframeIndex(cfg)
                for _, rows in data.chunks():
                    index.add(rows)
                t_build, c_build = time.perf_counter() - t0, time.process_time() - c0
                for ef in args.ef_sweep:
                    set_knob(index, "ef_search", ef)
                    t0 = time.process_time()
                    sims = [index.search(q, k=k)[1].numpy() for q in queries]
                    ms = 1e3 * (time.process_time() - t0) / nq
                    props = [index._structure.candidates(q, r_default, n) for q in queries]
                    share = np.mean([np.intersect1d(p, t[:r_default]).size / r_default for p, t in zip(props, top)])
                    print(f"| HNSW M {m}, ef_construction {efc} (build {t_build:.0f} s wall, {c_build:.0f} s CPU), "
                          f"ef_search {ef} | {r_default} | {recall(sims, ref)[0]:.3f} (graph proposes {share:.3f} "
                          f"of the code's top {r_default}; {ms:.2f} ms CPU a query) |", flush=True)
                del index
                _release()
            del store
            _release()


def _code_topr(code, x: np.ndarray, queries: np.ndarray, r: int) -> np.ndarray:
    """Rows ``(Q, r)`` of the ``r`` nearest codes to each query's code, by an exact scan of every row."""
    zq = torch.from_numpy(code.encode(queries))
    best_d = torch.full((zq.shape[0], r), float("inf"))
    best_i = torch.full((zq.shape[0], r), -1, dtype=torch.long)
    for lo in range(0, x.shape[0], 65536):
        z = torch.from_numpy(code.encode(x[lo: lo + 65536]))
        d = (z * z).sum(1)[None] - 2 * zq @ z.t()
        d_all = torch.cat([best_d, d], 1)
        i_all = torch.cat([best_i, torch.arange(lo, lo + z.shape[0]).expand(zq.shape[0], -1)], 1)
        best_d, pos = torch.topk(d_all, min(r, d_all.shape[1]), dim=1, largest=False)
        best_i = i_all.gather(1, pos)
    return best_i.numpy()


def _rescore(index: KeyframeIndex, q: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Exact similarities of the candidate rows, most similar first (as the index re-scores them)."""
    sims = index._store.rows(np.unique(rows[rows >= 0]), np.float64) @ q.astype(np.float64)
    return np.sort(sims.astype(np.float32))[::-1]


def crossover(args) -> None:
    """Exact scan vs the default structure, small sizes: where exact_below belongs."""
    print("\n### Exact scan vs the default structure at small sizes (clustered, D = 1024)\n")
    print("| keyframes | exact ms | default structure ms | ratio | structure recall@10 |")
    print("|---:|---:|---:|---:|---:|")
    for n in (1024, 2048, 4096, 8192, 16384):
        data = Clustered(n, args.dim)
        queries = data.queries(200)
        _, ref = exact_reference(data, queries, args.k)
        exact = KeyframeIndex(IndexConfig(backend="exact"))
        default = KeyframeIndex(IndexConfig(exact_below=n, background=False))
        for _, rows in data.chunks():
            exact.add(rows)
            default.add(rows)
        res = measure({"exact": exact, "default": default}, queries, ref, args.k, args.rounds, 200,
                      knobs={"exact": None, "default": None})
        (ms_e, *_), (ms_d, rec, _, _) = res[("exact", None, None)], res[("default", None, None)]
        print(f"| {n} | {ms_e:.3f} | {ms_d:.3f} | {ms_d / ms_e:.2f} | {rec:.3f} |", flush=True)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000],
                    help="keyframes in the synthetic databases")
    ap.add_argument("--dim", type=int, default=1024, help="descriptor dimension")
    ap.add_argument("--data", nargs="+", choices=["clustered", "hard", "real", "random"],
                    default=["clustered", "real"],
                    help="descriptor sets: clustered, hard, random (synthetic) and real (the kitchen's)")
    ap.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=None,
                    help=f"default: {' '.join(SYNTHETIC_VARIANTS)} (synthetic), all (--real-sets)")
    ap.add_argument("--storage", choices=["float32", "float16"], default="float32", help="index storage precision")
    ap.add_argument("--k", type=int, default=10, help="neighbours per query")
    ap.add_argument("--queries", type=int, default=200, help="queries per database")
    ap.add_argument("--exact-queries", type=int, default=200, help="queries the exact scan answers")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds")
    ap.add_argument("--keep-below", type=int, default=200_000,
                    help="sizes up to this keep every variant in memory and interleave their timings")
    ap.add_argument("--stream", type=int, default=1000, help="keyframes in the stream table (0: skip)")
    ap.add_argument("--stream-variants", nargs="+", default=["flann-pca128", "faiss-pca128"],
                    help="variants timed in the stream table")
    ap.add_argument("--build-threads", type=int, default=1, help="faiss OpenMP threads for builds")
    ap.add_argument("--real-sets", action="store_true", help="recall on the real descriptors themselves")
    ap.add_argument("--crossover", action="store_true", help="exact scan vs structure from 1k to 16k")
    ap.add_argument("--skip-synthetic", action="store_true", help="only the real descriptor sets")
    ap.add_argument("--diagnose", action="store_true",
                    help="split the default's loss: exact search on its PCA code vs HNSW graphs on that code")
    ap.add_argument("--diagnose-queries", type=int, default=100, help="queries of the diagnosis")
    ap.add_argument("--graphs", nargs="*", default=[], metavar="M:EFC",
                    help="HNSW graphs (links M, ef_construction) the diagnosis builds on the code")
    ap.add_argument("--ef-sweep", type=int, nargs="+", default=[64, 128, 256], help="ef_search of the diagnosis")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if faiss_available():
        import faiss

        faiss.omp_set_num_threads(args.build_threads)
    print(f"# keyframe index at scale ({platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"torch threads {torch.get_num_threads()}, faiss build threads {args.build_threads}, "
          f"load average {os.getloadavg()[0]:.1f}, {time.strftime('%Y-%m-%d %H:%M')})\n")
    print(f"defaults: IndexConfig() -> backend {KeyframeIndex().backend}, exact_below {DEFAULT.exact_below}, "
          f"reduce_dim {DEFAULT.reduce_dim}, rerank {DEFAULT.rerank}, {FlannConfig()}, {FaissConfig()}\n")
    need_real = args.real_sets or (not args.skip_synthetic and "real" in args.data)
    real = real_descriptors() if need_real else None
    if args.diagnose:
        diagnose(args, real)
    elif not args.skip_synthetic:
        synthetic(args, real)
    if args.real_sets:
        real_sets(args, real)
    if args.crossover:
        crossover(args)


if __name__ == "__main__":
    main()
