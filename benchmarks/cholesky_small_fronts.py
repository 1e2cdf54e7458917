"""The sparse Cholesky's small supernodes in C: the threshold ``_C_MAX_FRONT`` and the symbolic analysis.

1. Factor + solve of one damped normal-equation system (the optimiser's first, at the initial guess) with
   supernodes of at most T rows done by the C kernels (``slam.graph.accel._kernels.factor_group`` /
   ``solve_group``) and the others by LAPACK / torch, for several T (0 = no C kernels), on simulated
   graphs (``manhattan_world``) and the shared g2o files; median of ``--repeats``.
2. The symbolic analysis (``SymbolicCholesky(pattern)``) of M3500 with the per-size index helpers of
   ``_update_positions`` cached (the code) and made afresh at every call (as before), alternating.

Needs the C kernels (``slam.graph.compiled_kernels()``).

Usage:
    python benchmarks/cholesky_small_fronts.py [--data DIR] [--repeats 7] [--sizes 500 5000 20000] [--out FILE.md]
"""
from __future__ import annotations

import argparse
import datetime
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import slam.graph.cholesky as chol  # noqa: E402  (after the sys.path line)
from slam.graph import OptimizerConfig, compiled_kernels, read_g2o  # noqa: E402
from slam.graph.accel.host import host_problem  # noqa: E402
from slam.graph.simulate import manhattan_world  # noqa: E402

THRESHOLDS = [0, 16, 32, 64, 128, 256]
FILES = ["smallGrid3D", "sphere2500", "parking-garage", "input_M3500_g2o"]


def first_system(graph):
    """The sparse HostProblem of ``graph`` and its damped system ``(H + 1e-5 I, g)`` at the initial guess."""
    prob = host_problem(graph, OptimizerConfig(dense_max=0), None, "free", "auto", compiled=True)
    _, _, cache = prob.evaluate(prob.poses)
    H, g = prob.linearize(prob.poses, cache)
    Hd = H.copy()
    Hd[prob.diag_pos] += 1e-5
    return prob, Hd, g


def factor_solve_ms(prob, Hd, g, threshold: int, repeats: int) -> float:
    chol._C_MAX_FRONT = threshold
    sym = chol.SymbolicCholesky(prob.pattern)  # a fresh workspace: the threshold is read when it is made
    sym.factor(Hd).solve(-g)  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        sym.factor(Hd).solve(-g)
        times.append(time.perf_counter() - t)
    return 1e3 * statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=None, help="folder holding posegraph/ (default $ATTNLOOP_DATA or ../shared/data)")
    ap.add_argument("--repeats", type=int, default=7, help="timing repeats per threshold (the median is reported)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[500, 5000, 20000], help="poses of the simulated graphs (manhattan_world)")
    ap.add_argument("--out", default=None, help="also write the markdown here")
    args = ap.parse_args()
    if not compiled_kernels():
        sys.exit("the C kernels slam.graph.accel._kernels were not built: nothing to compare")
    data = Path(args.data or os.environ.get("ATTNLOOP_DATA", ROOT.parent / "shared" / "data")) / "posegraph"
    default = chol._C_MAX_FRONT
    lines = [f"Command: `python benchmarks/cholesky_small_fronts.py --repeats {args.repeats}`, "
             f"{datetime.datetime.now():%Y-%m-%d %H:%M}, {os.cpu_count()} CPUs, load average "
             f"{os.getloadavg()[0]:.1f} at start; `_C_MAX_FRONT` = {default} in the code.", "",
             "Factor + solve of one system, ms (median); columns: the largest front (rows) the C kernels take "
             "(0: none).", "",
             "| graph | unknowns | " + " | ".join(f"T = {t}" for t in THRESHOLDS) + " |",
             "|---|---|" + "---|" * len(THRESHOLDS)]
    print("\n".join(lines), flush=True)
    graphs = [(f"manhattan_world({n})", lambda n=n: manhattan_world(n, seed=0, sigma_r=0.003).graph)
              for n in args.sizes]
    graphs += [(name, lambda name=name: read_g2o(data / f"{name}.g2o")) for name in FILES
               if (data / f"{name}.g2o").exists()]
    try:
        for name, make in graphs:
            prob, Hd, g = first_system(make())
            ms = [factor_solve_ms(prob, Hd, g, t, args.repeats) for t in THRESHOLDS]
            row = f"| {name} | {prob.size} | " + " | ".join(f"{m:.2f}" for m in ms) + " |"
            lines.append(row)
            print(row, flush=True)
    finally:
        chol._C_MAX_FRONT = default
    m3500 = data / "input_M3500_g2o.g2o"
    if m3500.exists():
        prob, _, _ = first_system(read_g2o(m3500))
        cached = chol._tril_and_tri

        def fresh(r, h):
            return (*np.tril_indices(r), np.tri(h, dtype=bool).T)

        times = {"cached": [], "fresh": []}
        try:
            for _ in range(3 * args.repeats):
                for key, fn in (("cached", cached), ("fresh", fresh)):
                    chol._tril_and_tri = fn
                    t = time.perf_counter()
                    chol.SymbolicCholesky(prob.pattern)
                    times[key].append(time.perf_counter() - t)
        finally:
            chol._tril_and_tri = cached
        row = (f"Symbolic analysis of M3500 (median of {3 * args.repeats}, alternating): index helpers made once "
               f"per size {1e3 * statistics.median(times['cached']):.1f} ms, made at every call "
               f"{1e3 * statistics.median(times['fresh']):.1f} ms.")
        lines += ["", row]
        print("\n" + row, flush=True)
    if args.out:
        Path(args.out).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
