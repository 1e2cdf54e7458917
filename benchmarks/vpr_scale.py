"""attnloop-vpr at scale: describe throughput of both engines, their agreement, and the sharded index.

1. Throughput on real images (rtabmap-samples' 84, ``--repeat`` times): the descriptor alone on images decoded
   beforehand, a plain batched loop over the descriptor (decode, then ``model(batch)``, in this process), the
   local engine (:func:`attnloop.vpr.describe`:
   a DataLoader worker decodes, shards and manifest written), and Ray Data with 1 and 2 actors of one CPU
   each (Ray started before the clock, the actors' model build inside it). One torch thread per model; each
   way ``--rounds`` times, interleaved, the best round reported (other work shares the CPU).
2. The engines' agreement: the same paths in order, the largest difference between their descriptors.
3. Memory: bytes per descriptor in the shards, per million descriptors.
4. The sharded index (:class:`attnloop.vpr.ShardedIndex`) against one index on ``--index-size`` synthetic unit
   descriptors (benchmarks.index's "clustered" places): queries with the same top 10, recall@10 against the
   exact top 10, and the time a query.

Usage:
    OMP_NUM_THREADS=1 python -m benchmarks.vpr_scale [--repeat 2] [--index-size 1000000] [--shards 4]
    python -m benchmarks.vpr_scale --skip-describe --index-size 100000 --backend faiss   # the HNSW graph
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from attnloop.index import IndexConfig
from attnloop.vpr import ShardedIndex, describe, load_descriptors
from attnloop.vpr.describe import describe_batch, load_rgb
from benchmarks._common import add_data_argument, table
from benchmarks.index_data import Clustered, exact_reference


def _model():
    from slam.config import DescriptorConfig
    from slam.loop.closer import build_descriptor

    settings = DescriptorConfig(backbone="efficientnet_lite0")
    return build_descriptor(settings), {**settings.__dict__}


def plain_loop(model, paths: list[str], batch: int) -> np.ndarray:
    """Decode and describe in order, ``batch`` images at a time, in this process: the reference loop."""
    rows = []
    for s in range(0, len(paths), batch):
        decoded = [(i, load_rgb(p), None) for i, p in enumerate(paths[s:s + batch])]
        rows += [r for _, r, _ in describe_batch(model, decoded)]
    return np.stack(rows)


def throughput(paths: list[str], batch: int, skip_ray: bool, rounds: int) -> tuple[list[list], dict]:
    """Each way to describe ``paths``, ``rounds`` times interleaved (the CPU is shared: the best round counts)."""
    torch.set_num_threads(1)
    model, settings = _model()
    plain_loop(model, paths[:1], batch)  # the first call's one-off costs are no engine's
    decoded = [(i, load_rgb(p), None) for i, p in enumerate(paths)]
    out: dict = {}
    tmp = Path(tempfile.mkdtemp())

    def engine(name, **kw):
        shutil.rmtree(tmp / name, ignore_errors=True)
        describe(paths, tmp / name, model, settings, progress=False, batch_size=batch, **kw)
        out[name] = load_descriptors(tmp / name)

    ways = [("the descriptor alone (images decoded beforehand)", 1,
             lambda: [list(describe_batch(model, decoded[s:s + batch])) for s in range(0, len(paths), batch)]),
            ("plain batched loop (decode, describe)", 1, lambda: out.update(plain=plain_loop(model, paths, batch))),
            ("local engine (1 decoding worker)", 1, lambda: engine("local", workers=1))]
    if not skip_ray:
        import ray

        ray.init(include_dashboard=False, log_to_driver=False, num_cpus=2)
        ways += [(f"Ray Data, {n} actor(s) x 1 CPU", n, lambda n=n: engine(f"ray{n}", engine="ray", actors=n))
                 for n in (1, 2)]
    best = {name: float("inf") for name, _, _ in ways}
    for _ in range(rounds):
        for name, _, fn in ways:
            t = time.perf_counter()
            fn()
            best[name] = min(best[name], time.perf_counter() - t)
    if not skip_ray:
        ray.shutdown()
    out["bytes_per_row"] = (tmp / "local" / "shard-00000.npy").stat().st_size / len(paths)
    shutil.rmtree(tmp)
    return [[name, n, f"{best[name]:.1f}", f"{len(paths) / best[name]:.2f}", f"{len(paths) / best[name] / n:.2f}"]
            for name, n, _ in ways], out


def sharded_index(n: int, dim: int, shards: int, backend: str, queries: int, k: int = 10) -> list:
    """One index against ``shards`` indexes on the "clustered" set of benchmarks.index (places of ~20 views,
    cosine 0.5 between views; the queries are new views): the same top 10, and each one's recall@10 against
    the exact top 10."""
    data = Clustered(n, dim)
    x = np.concatenate([rows for _, rows in data.chunks()])
    q = data.queries(queries)
    exact = exact_reference(data, q, k)[0] if backend != "exact" else None
    config = IndexConfig(backend=backend, background=False)
    answers, rows = {}, []
    for name, max_rows in (("one index", n), (f"{shards} shards", -(-n // shards))):
        t = time.perf_counter()
        index = ShardedIndex.build(x, config, max_rows=max_rows)
        build = time.perf_counter() - t
        times, ids = [], []
        for i in range(queries):
            t = time.perf_counter()
            ids.append(index.search(q[i:i + 1], k=k)[0][0].numpy())
            times.append(time.perf_counter() - t)
        answers[name] = np.stack(ids)
        recall = 1.0 if exact is None else np.mean([len(set(a) & set(b)) / k for a, b in zip(answers[name], exact)])
        rows.append([name, len(index.indexes), f"{build:.1f}", f"{1000 * np.median(times):.1f}", f"{recall:.4f}"])
        del index
    one, sharded = answers.values()
    rows[1].append(f"{np.mean([np.array_equal(a, b) for a, b in zip(one, sharded)]):.3f}")
    rows[0].append("-")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_data_argument(parser)
    parser.add_argument("--repeat", type=int, default=2, help="describe the 84 rtabmap images this many times (2)")
    parser.add_argument("--rounds", type=int, default=2, help="timed rounds of each way, interleaved; the best "
                        "counts (2)")
    parser.add_argument("--batch", type=int, default=16, help="images per batch (16)")
    parser.add_argument("--skip-describe", action="store_true", help="only the index")
    parser.add_argument("--skip-ray", action="store_true", help="no Ray rows")
    parser.add_argument("--index-size", type=int, default=1_000_000, help="synthetic descriptors indexed (10^6)")
    parser.add_argument("--dim", type=int, default=256, help="their dimension (256)")
    parser.add_argument("--shards", type=int, default=4, help="indexes of the sharded index (4)")
    parser.add_argument("--backend", default="exact", choices=("exact", "flann", "faiss"), help="index backend")
    parser.add_argument("--queries", type=int, default=200, help="queries: new views of stored places (200)")
    args = parser.parse_args()
    print(f"# attnloop-vpr at scale ({time.strftime('%Y-%m-%d %H:%M')}, torch {torch.__version__}, "
          f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f})")
    if not args.skip_describe:
        paths = [str(args.data / "rtabmap-samples" / f"{i}.jpg") for i in range(1, 85)] * args.repeat
        rows, out = throughput(paths, args.batch, args.skip_ray, args.rounds)
        print(f"\n## Describe: {len(paths)} images (rtabmap-samples x {args.repeat}), EfficientNet-Lite0 default, "
              f"batch {args.batch}\n")
        print(table(["engine", "workers", "s", "images/s", "images/s per worker"], rows))
        local_paths, local = out["local"]
        print(f"\nlocal engine vs plain loop: max |difference| {np.abs(local - out['plain']).max():.2e}")
        for name in ("ray1", "ray2"):
            if name in out:
                print(f"{name} vs local: same paths in order {out[name][0] == local_paths}, max |difference| "
                      f"{np.abs(out[name][1] - local).max():.2e}")
        print(f"shards: {out['bytes_per_row']:.0f} bytes a descriptor ({local.shape[1]}-d float32): "
              f"{out['bytes_per_row'] * 1e6 / 2 ** 30:.2f} GiB per million descriptors (load {os.getloadavg()[0]:.1f})")
    print(f"\n## Sharded index: {args.index_size} clustered unit {args.dim}-d descriptors, backend {args.backend}, "
          f"{args.queries} queries, top 10\n")
    print(table(["index", "indexes", "build s", "ms a query (median)", "recall@10 vs exact", "same top-10 as one"],
                sharded_index(args.index_size, args.dim, args.shards, args.backend, args.queries)))
    print(f"\n(load {os.getloadavg()[0]:.1f} at the end)")


if __name__ == "__main__":
    main()
