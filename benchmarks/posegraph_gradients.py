"""Gradients of optimised pose graphs (``optimize(..., differentiable=True)``): accuracy and cost.

For each file (default smallGrid3D and sphere2500; float64, the torch backend):

1. Accuracy: the directional derivative of ``<w, optimised poses>`` along a random change ``u`` of the
   measurements' translations, by implicit differentiation (autograd through ``slam.graph.implicit``) and by
   central differences of re-optimised poses (steps ``--step`` and twice it, Richardson-extrapolated; each
   optimum from LM to its lambda limit and Gauss-Newton steps after it, pose 0 held as the free gauge's
   result holds it). Also with the
   Gauss-Newton matrix ``2 J^T Omega J`` in place of the exact Hessian (what an implicit layer that reuses
   the solver's system would use): why the exact one.
2. Cost: the default call from the file's initial guess with and without ``differentiable=True``, and the
   backward pass, medians of ``--repeats``.

Usage:
    python -m benchmarks.posegraph_gradients [--data DIR] [--files smallGrid3D sphere2500] [--trials 3]
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]

from slam.graph import OptimizerConfig, edge_jacobians, edge_residuals, implicit, optimize, read_g2o
from slam.graph.problem import TorchProblem
from slam.lie import se3_normalize

F64 = torch.float64
TIGHT = dict(rel_tol=0.0, abs_tol=0.0)


def optimum(graph, **kw):
    """Optimised poses to round-off: LM to its lambda limit (it stops on the cost, so leaves the poses
    ~sqrt(eps) away), then plain Gauss-Newton steps, taken whatever the cost says (at this level the cost
    cannot tell a better pose from a worse one), pose 0 held as the free gauge's result holds it."""
    P = optimize(graph, **TIGHT, **kw).graph.poses.detach()
    prob = TorchProblem(graph.with_poses(P), OptimizerConfig(), None, "first", "auto")
    x = prob.poses
    for _ in range(8):
        H, g = prob.linearize(x, prob.evaluate(x)[2])
        x = prob.retract(x, prob.solve(H, g, 0.0))
    return x


def gauss_newton_hessians(spec, x, meas, info, poses):
    """``2 J^T Omega J`` per edge ``(E, 12, 12)``: the Gauss-Newton matrix in place of the exact Hessian."""
    r, D = edge_residuals(x, spec.ii, spec.jj, se3_normalize(meas, positive_w=False), spec.chart)
    Ji, Jj = edge_jacobians(x, spec.ii, spec.jj, D, r, spec.chart)
    J = torch.cat([Ji, Jj], -1)
    return 2.0 * J.mT @ (0.5 * (info + info.mT)) @ J


def directional(graph, u, w, hessians=None):
    """Implicit directional derivative of <w, poses> along u (measurements), with the given Hessian rule."""
    z = graph.measurements.clone().requires_grad_(True)
    saved = implicit._edge_hessians
    if hessians is not None:
        implicit._edge_hessians = hessians
    try:
        res = optimize(dataclasses.replace(graph, measurements=z), differentiable=True, **TIGHT)
        (res.graph.poses * w).sum().backward()
    finally:
        implicit._edge_hessians = saved
    return float((z.grad * u).sum())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=None, help="folder holding posegraph/ (default $ATTNLOOP_DATA or ../shared/data)")
    ap.add_argument("--files", nargs="+", default=["smallGrid3D", "sphere2500"],
                    help="g2o files of the shared posegraph folder")
    ap.add_argument("--trials", type=int, default=3, help="random (u, w) pairs per file")
    ap.add_argument("--step", type=float, default=1e-3, help="central-difference step on the translations (m)")
    ap.add_argument("--repeats", type=int, default=5, help="timing repeats (the median is reported)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    data = Path(args.data or os.environ.get("ATTNLOOP_DATA", ROOT.parent / "shared" / "data")) / "posegraph"
    lines = [f"Command: `python -m benchmarks.posegraph_gradients --files {' '.join(args.files)} --trials "
             f"{args.trials} --step {args.step:g}`, {datetime.datetime.now():%Y-%m-%d %H:%M}, {os.cpu_count()} CPUs, "
             f"load average {os.getloadavg()[0]:.1f} at start, torch {torch.__version__}, float64, torch backend.",
             "", "| file | poses | edges | trial | central difference | implicit (exact Hessian) | rel. error | "
             "implicit (Gauss-Newton matrix) | rel. error |", "|---|---|---|---|---|---|---|---|---|"]
    costs = []
    for name in args.files:
        path = data / f"{name}.g2o"
        if not path.exists():
            print(f"skipping {path}: not found", file=sys.stderr)
            continue
        start = read_g2o(path)
        graph = start.with_poses(optimum(start))  # a warm start for the differences below
        gen = torch.Generator().manual_seed(0)
        for trial in range(args.trials):
            u = torch.zeros(graph.num_edges, 7, dtype=F64)
            u[:, :3] = torch.randn(graph.num_edges, 3, generator=gen, dtype=F64)
            w = torch.randn(graph.num_poses, 7, generator=gen, dtype=F64)
            h = args.step

            def value(s):
                moved = dataclasses.replace(graph, measurements=graph.measurements + s * u)
                return float((optimum(moved) * w).sum())

            # Richardson: steps h and 2 h, their h^2 errors cancelled (a larger step averages out the
            # re-optimised poses' round-off, ~1e-10)
            fd = (4 * (value(h) - value(-h)) / (2 * h) - (value(2 * h) - value(-2 * h)) / (4 * h)) / 3
            exact = directional(graph, u, w)
            gn = directional(graph, u, w, gauss_newton_hessians)
            row = (f"| {name} | {graph.num_poses} | {graph.num_edges} | {trial} | {fd:.8g} | {exact:.8g} | "
                   f"{abs(exact - fd) / abs(fd):.1e} | {gn:.8g} | {abs(gn - fd) / abs(fd):.1e} |")
            lines.append(row)
            print(row, flush=True)
        # cost: the default call from the file's initial guess, and one backward pass
        z = start.measurements.clone().requires_grad_(True)
        g = dataclasses.replace(start, measurements=z)
        optimize(g, differentiable=True).graph.poses.sum().backward()  # warm-up
        fwd, bwd, plain = [], [], []
        for _ in range(args.repeats):
            t = time.perf_counter()
            optimize(start)
            plain.append(time.perf_counter() - t)
            t = time.perf_counter()
            res = optimize(g, differentiable=True)
            fwd.append(time.perf_counter() - t)
            t = time.perf_counter()
            res.graph.poses.sum().backward()
            bwd.append(time.perf_counter() - t)
        costs.append(f"| {name} | {1e3 * statistics.median(plain):.1f} | {1e3 * statistics.median(fwd):.1f} | "
                     f"{1e3 * statistics.median(bwd):.1f} | {statistics.median(bwd) / statistics.median(plain):.2f} |")
        print(costs[-1], flush=True)
    lines += ["", "Cost (median ms; the default call from the file's initial guess, and the backward pass of a "
              "scalar of all poses):", "",
              "| file | optimize | optimize(differentiable=True) | backward | backward / optimize |",
              "|---|---|---|---|---|"] + costs
    print()
    print("\n".join(lines))


if __name__ == "__main__":
    main()
