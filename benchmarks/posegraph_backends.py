"""The optimiser's CPU backends side by side, and where a dense solve beats the sparse one.

1. ``optimize`` timed without GTSAM in between (median of ``--repeats``, the backends interleaved) on
   every pose-graph file, with the torch reference (``slam.graph.fused``) and the accelerator
   (``slam.graph.accel``): its numpy functions and its C kernels (``slam.graph.accel._kernels``): the effect of
   each, and a check that all reach the same chi2 in the same iterations.
2. With ``--subgraphs``, the dense/sparse crossover behind ``OptimizerConfig.dense_max = None``: sphere2500's
   first N poses (the edges among them) solved with ``dense_max=0`` (always sparse) and with a large one
   (always dense), for each backend.

Usage:
    python benchmarks/posegraph_backends.py [--data DIR] [--repeats 15] [--subgraphs] [--out FILE.md]
"""
from __future__ import annotations

import argparse
import datetime
import os
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from slam.graph import PoseGraph, compiled_kernels, optimize, read_g2o  # noqa: E402  (after the sys.path line)

FILES = ["tinyGrid3D", "smallGrid3D", "sphere2500", "parking-garage", "input_M3500_g2o", "input_INTEL_g2o"]
SUBGRAPH_POSES = [20, 40, 60, 70, 80, 100]


def median_ms(fns: dict, repeats: int) -> dict:
    """Median ms of each callable, interleaved (A, B, C, A, B, C, ...: a change of the machine's load hits
    all alike) after a warm-up call each (lazy imports, first-touch allocations)."""
    for fn in fns.values():
        fn()
    times = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t)
    return {k: 1e3 * statistics.median(v) for k, v in times.items()}


def first_poses(graph: PoseGraph, n: int) -> PoseGraph:
    """The first ``n`` poses and the edges among them."""
    keep = (graph.ii < n) & (graph.jj < n)
    return PoseGraph(graph.poses[:n], graph.ii[keep], graph.jj[keep], graph.measurements[keep],
                     graph.information[keep])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default=None, help="folder holding posegraph/ (default $ATTNLOOP_DATA or ../shared/data)")
    p.add_argument("--repeats", type=int, default=15, help="timing repeats (the median is reported)")
    p.add_argument("--out", default=None, help="also write the markdown here")
    p.add_argument("--subgraphs", action="store_true", help="also time dense vs sparse on sphere2500's first poses")
    args = p.parse_args()
    data = Path(args.data or os.environ.get("ATTNLOOP_DATA", ROOT.parent / "shared" / "data")) / "posegraph"
    if not data.is_dir():
        sys.exit(f"pose-graph files not found at {data} (set --data or ATTNLOOP_DATA)")
    lines = [f"Command: `python benchmarks/posegraph_backends.py --repeats {args.repeats}"
             + (" --subgraphs" if args.subgraphs else "") + "`, "
             f"{datetime.datetime.now():%Y-%m-%d %H:%M}, {os.cpu_count()} CPUs, load average "
             f"{os.getloadavg()[0]:.1f} at start, torch {torch.__version__}.", ""]
    backends = ("torch", "numpy", "c") if compiled_kernels() else ("torch", "numpy")
    if not compiled_kernels():
        lines += ["The C kernels were not built: no \"c\" columns.", ""]
    lines += ["| file | " + " | ".join(f"{b} ms" for b in backends) + " | torch / numpy"
              + (" | numpy / c | torch / c" if "c" in backends else "") + " | "
              + " | ".join(f"chi2/2 {b}" for b in backends)
              + " | iterations " + " / ".join(backends) + " |",
              "|---" * (2 * len(backends) + 3 + 2 * ("c" in backends)) + "|"]
    print("\n".join(lines), flush=True)
    for name in FILES:
        path = data / f"{name}.g2o"
        if not path.exists():
            continue
        g = read_g2o(path)
        reps = args.repeats if g.num_edges < 2000 else max(3, args.repeats // 3)
        res = {b: optimize(g, backend=b) for b in backends}
        ms = median_ms({b: (lambda b=b: optimize(g, backend=b)) for b in backends}, reps)
        row = (f"| {name} | " + " | ".join(f"{ms[b]:.2f}" for b in backends) + f" | {ms['torch'] / ms['numpy']:.2f}"
               + (f" | {ms['numpy'] / ms['c']:.2f} | {ms['torch'] / ms['c']:.2f}" if "c" in backends else "") + " | "
               + " | ".join(f"{res[b].chi2 / 2:.6f}" for b in backends) + " | "
               + " / ".join(str(res[b].iterations) for b in backends) + " |")
        lines.append(row)
        print(row, flush=True)
    sphere = data / "sphere2500.g2o"
    if sphere.exists() and args.subgraphs:
        g = read_g2o(sphere)
        head = ["", "Dense vs sparse solve, sphere2500's first N poses (ms, median):", "",
                "| poses | unknowns | edges | "
                + " | ".join(f"{b} {d}" for b in backends[::-1] for d in ("sparse", "dense")) + " |",
                "|---" * (3 + 2 * len(backends)) + "|"]
        lines += head
        print("\n".join(head), flush=True)
        for n in SUBGRAPH_POSES:
            sub = first_poses(g, n)
            ms = list(median_ms({(b, d): (lambda b=b, d=d: optimize(sub, backend=b, dense_max=d))
                                 for b in backends[::-1] for d in (0, 10 ** 6)}, args.repeats).values())
            row = f"| {n} | {6 * n} | {sub.num_edges} | " + " | ".join(f"{m:.2f}" for m in ms) + " |"
            lines.append(row)
            print(row, flush=True)
    if args.out:
        Path(args.out).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
