"""Benchmark of the keyframe database (attnloop.index): build time, query time, recall@k vs checks.

Data: synthetic 1024-d unit descriptors. "easy", "clustered", "hard": keyframes of N/20 places, each
view = place + noise of norm 0.6 / 1.0 / 1.5 (cosine between two views of one place ~0.74 / 0.5 / 0.3,
between places ~0), the structure of a SLAM database; "random": i.i.d. Gaussian directions, the worst case
for any tree (no structure to exploit). Queries are new views of stored places. Recall@k (the fraction of
the exact top-k returned) and "top-1 found" (the exact nearest neighbour is among the k returned) are
measured against the exact search on the same data. Also measured: the exact scan that the tree
replaces, and a keyframe-by-keyframe stream (add + query per keyframe, background rebuilds) as the SLAM
system uses it.

Usage:
    python benchmarks/index.py     # sizes 1e3 1e4 1e5; clustered, hard, random; stream of 1e4 keyframes
    python benchmarks/index.py --sizes 1000 10000 --data random --checks 64 -1 --stream 0

Prints markdown tables.
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

from attnloop.index import IndexConfig, KeyframeIndex, LoopCandidateDetector, LoopDetectorConfig
from attnloop.threshold import ThresholdConfig

SPREAD = {"easy": 0.6, "clustered": 1.0, "hard": 1.5}


def make_data(n: int, d: int, kind: str, n_queries: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)

    def unit(x):
        return x / x.norm(dim=-1, keepdim=True)

    if kind == "random":
        return unit(torch.randn(n, d, generator=g)), unit(torch.randn(n_queries, d, generator=g))
    places = unit(torch.randn(max(n // 20, 1), d, generator=g))
    labels = torch.randint(0, places.shape[0], (n,), generator=g)
    spread = SPREAD[kind]
    db = unit(places[labels] + spread * unit(torch.randn(n, d, generator=g)))
    qlab = torch.randint(0, places.shape[0], (n_queries,), generator=g)
    queries = unit(places[qlab] + spread * unit(torch.randn(n_queries, d, generator=g)))
    return db, queries


def exact_topk(db: np.ndarray, q: np.ndarray, k: int) -> np.ndarray:
    # torch's matrix-vector product (what the index's exact scans use): numpy's was erratic when busy.
    sims = (torch.from_numpy(db) @ torch.from_numpy(q)).numpy()
    top = np.argpartition(-sims, k - 1)[:k]
    return top[np.argsort(-sims[top])]


def timed(fn, repeat: int = 1):
    t0 = time.perf_counter()
    for _ in range(repeat):
        out = fn()
    return (time.perf_counter() - t0) / repeat, out


def bench_size(n: int, d: int, kind: str, k: int, checks_list, n_queries: int, cfg_kw: dict) -> list[str]:
    db, queries = make_data(n, d, kind, n_queries)
    db_np, q_np = db.numpy(), queries.numpy()
    # exact reference and its cost
    t_exact, ref = timed(lambda: [exact_topk(db_np, q, k) for q in q_np])
    ms_exact = 1e3 * t_exact / n_queries
    # No automatic build while adding; the build is timed on its own.
    index = KeyframeIndex(IndexConfig(min_tree_size=1, rebuild_every=10**9, background=False, **cfg_kw))
    index.add(db)
    t_build, _ = timed(index.rebuild)
    assert index.n_indexed == n
    rows = []
    for checks in checks_list:
        index.config.checks = checks
        index.search(queries[0], k=k)  # warm-up
        t, res = timed(lambda: [index.search(q, k=k)[0].numpy() for q in queries])
        recall = np.mean([len(set(a.tolist()) & set(b.tolist())) / k for a, b in zip(res, ref)])
        top1 = np.mean([b[0] in set(a.tolist()) for a, b in zip(res, ref)])
        rows.append(f"| {kind} | {n:>7} | {t_build:8.2f} | {checks:>6} | {1e3 * t / n_queries:8.3f} | "
                    f"{recall:6.3f} | {top1:6.3f} | {ms_exact:8.3f} |")
    return rows


def bench_stream(n: int, d: int, kind: str, k: int, window: int, cfg_kw: dict) -> str:
    db, _ = make_data(n, d, kind, 1)
    index = KeyframeIndex(IndexConfig(background=True, **cfg_kw))
    lat = np.zeros(n)
    t_all = time.perf_counter()
    for i in range(n):
        t0 = time.perf_counter()
        index.search(db[i], k=k, max_id=i - window)
        index.add(db[i], ids=[i])
        lat[i] = time.perf_counter() - t0
    total = time.perf_counter() - t_all
    index.wait()
    return (f"| {kind} | {n} | {1e3 * lat.mean():.3f} | {1e3 * np.percentile(lat, 99):.3f} | "
            f"{1e3 * lat.max():.1f} | {index.num_builds} | {total:.1f} |")


# ----------------------------------------------------------------------------------------------
# Threshold and detector on real descriptors (7-Scenes redkitchen)
# ----------------------------------------------------------------------------------------------
def redkitchen_descriptors(root: Path, modes, backbone: str, cache: Path) -> dict:
    """Descriptors of every frame for each fusion mode + ground-truth poses, cached in ``cache``."""
    cache.parent.mkdir(parents=True, exist_ok=True)
    if cache.is_file():
        return torch.load(cache)
    import cv2

    from attnloop import AttentionDescriptor  # the public descriptor (issue 2)

    files = sorted(root.glob("frame-*.color.jpg"))
    if not files:
        raise SystemExit(f"no frame-*.color.jpg in {root} (set ATTNLOOP_DATA)")
    poses = torch.from_numpy(np.stack([np.loadtxt(str(f).replace("color.jpg", "pose.txt")) for f in files]))
    out = {"poses": poses}
    for mode in modes:
        model = AttentionDescriptor(backbone=backbone, fusion=mode, pretrained=True).eval()
        chunks = []
        for s in range(0, len(files), 8):
            imgs = [cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB) for f in files[s: s + 8]]
            x = torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).contiguous()
            chunks.append(model(x).detach())
        out[mode] = torch.cat(chunks)
    torch.save(out, cache)
    return out


def gt_matches(T: np.ndarray, max_dist: float, max_angle_deg: float) -> np.ndarray:
    """(N, N) bool: frames closer than max_dist metres and max_angle_deg degrees (camera-to-world T)."""
    t, R = T[:, :3, 3], T[:, :3, :3]
    dist = np.linalg.norm(t[:, None] - t[None], axis=-1)
    cos = np.clip((np.einsum("iab,jab->ij", R, R) - 1.0) / 2.0, -1.0, 1.0)
    return (dist < max_dist) & (np.degrees(np.arccos(cos)) < max_angle_deg)


def detector_eval(desc: torch.Tensor, gt: np.ndarray, window: int, k_sigma: float) -> str:
    """Run LoopCandidateDetector over all frames (id = frame index) and score its output by ground truth."""
    cfg = LoopDetectorConfig(window=window, threshold=ThresholdConfig(k_sigma=k_sigma))
    det = LoopCandidateDetector(cfg)
    n = desc.shape[0]
    top_true = top_false = cand_true = cand_false = with_match = 0
    for i in range(n):
        out = det.add_and_query(desc[i], keyframe_id=i)
        if i - window >= 0 and gt[i, : i - window + 1].any():
            with_match += 1
        ids = out.ids.tolist()
        if ids:
            top_true += bool(gt[i, ids[0]])
            top_false += not gt[i, ids[0]]
            good = sum(bool(gt[i, j]) for j in ids)
            cand_true += good
            cand_false += len(ids) - good
    prec = top_true / max(top_true + top_false, 1)
    cprec = cand_true / max(cand_true + cand_false, 1)
    return (f"| {window} | {k_sigma:g} | {with_match} | {top_true + top_false} | {prec:.3f} | "
            f"{top_true / max(with_match, 1):.3f} | {cand_true + cand_false} | {cprec:.3f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10_000, 100_000])
    ap.add_argument("--dim", type=int, default=1024)
    ap.add_argument("--data", nargs="+", choices=["easy", "clustered", "hard", "random"],
                    default=["clustered", "hard", "random"])
    ap.add_argument("--checks", type=int, nargs="+", default=[32, 128, 256, 512, 2048, -1])
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--queries", type=int, default=200)
    ap.add_argument("--branching", type=int, default=IndexConfig.branching)
    ap.add_argument("--iterations", type=int, default=IndexConfig.iterations)
    ap.add_argument("--stream", type=int, default=10_000, help="keyframes in the add+query stream (0: skip)")
    ap.add_argument("--threads", type=int, default=0, help="torch/numpy threads (0: leave as is)")
    ap.add_argument("--redkitchen", action="store_true",
                    help="also evaluate the threshold/detector on 7-Scenes redkitchen descriptors")
    ap.add_argument("--fusion", nargs="+", default=["none", "dam"], help="modes for --redkitchen")
    ap.add_argument("--backbone", default="efficientnet_lite0", help="backbone for --redkitchen")
    ap.add_argument("--descriptors", type=Path, default=None,
                    help="descriptor cache for --redkitchen (default out/index_<backbone>_redkitchen.pt)")
    ap.add_argument("--windows", type=int, nargs="+", default=[30, 150], help="exclusion windows (frames)")
    ap.add_argument("--k-sigma", type=float, nargs="+", default=[2.0, 3.0, 4.0, 5.0])
    ap.add_argument("--skip-synthetic", action="store_true")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    cfg_kw = dict(branching=args.branching, iterations=args.iterations)
    kinds = args.data
    print(f"# keyframe index benchmark ({platform.processor() or platform.machine()}, "
          f"torch threads {torch.get_num_threads()}, D={args.dim}, k={args.k}, branching={args.branching}, "
          f"iterations={args.iterations}, {time.strftime('%Y-%m-%d')})\n")
    if not args.skip_synthetic:
        synthetic(args, kinds, cfg_kw)
    if args.redkitchen:
        real(args)


def real(args) -> None:
    root = Path(os.environ.get("ATTNLOOP_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    cache = args.descriptors or Path("out") / f"index_{args.backbone}_redkitchen.pt"
    data = redkitchen_descriptors(root / "7scenes-redkitchen", args.fusion, args.backbone, cache)
    gt = gt_matches(data["poses"].numpy(), 0.5, 45.0)
    print(f"\n7-Scenes redkitchen, {args.backbone}, every frame a keyframe (id = frame index); a match is "
          "true when the frames are < 0.5 m and < 45 deg apart by ground truth. Default detector "
          "(top_k 5, MAD threshold) with the given window and k_sigma.\n")
    for mode in args.fusion:
        if mode not in data:
            print(f"(no descriptors for mode {mode} in {cache})")
            continue
        print(f"\n{mode}:\n")
        print("| window | k_sigma | queries with a true match | top-1 accepted | top-1 precision "
              "| top-1 recall | candidates accepted | candidate precision |")
        print("|---:|---:|---:|---:|---:|---:|---:|---:|")
        for w in args.windows:
            for k in args.k_sigma:
                print(detector_eval(data[mode].float(), gt, w, k), flush=True)


def synthetic(args, kinds, cfg_kw) -> None:
    print(f"| data | keyframes | build s | checks | query ms | recall@{args.k} | top-1 found "
          "| exact scan ms |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for kind in kinds:
        for n in args.sizes:
            for row in bench_size(n, args.dim, kind, args.k, args.checks, args.queries, cfg_kw):
                print(row, flush=True)
    if args.stream:
        print(f"\nStream: one search (k={args.k}, window 30) + one add per keyframe, background rebuilds "
              "(rebuild_every/rebuild_fraction defaults).\n")
        print("| data | keyframes | mean ms | p99 ms | max ms | builds | total s |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for kind in kinds[:1]:
            print(bench_stream(args.stream, args.dim, kind, args.k, 30, cfg_kw), flush=True)


if __name__ == "__main__":
    main()
