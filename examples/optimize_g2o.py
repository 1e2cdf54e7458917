"""Optimise a g2o pose graph with slam.graph (the job of g2o's or GTSAM's command-line examples).

    python examples/optimize_g2o.py ../shared/data/posegraph/sphere2500.g2o -o sphere2500_opt.g2o
    python examples/optimize_g2o.py noisy.g2o --kernel cauchy --gauge first
    python examples/optimize_g2o.py sphere_bignoise.g2o --initialization chordal
    python examples/optimize_g2o.py warm_start.g2o --initialization none

Reads ``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT`` or 2D ``VERTEX_SE2`` / ``EDGE_SE2`` files (``FIX`` lines are
held; a file with edges only gets its poses from a spanning tree of the edges). The start is by default
the poses composed along a breadth-first spanning tree of the edges: a file's vertices are often raw
odometry, from which LM crawls on input_INTEL_g2o.g2o (100 iterations to chi2 109,178, where this start
converges in 5 to 215.84; on the other shared files one iteration fewer, on tinyGrid3D one more). ``chordal``
(GTSAM's InitializePose3) is the start for large measurement noise; ``none`` keeps the file's vertices (a
solution to refine). The script prints the cost before and after (chi2 = sum r^T Omega r; GTSAM's error is
chi2 / 2), the iterations, the status and the time split, and writes the optimised graph (2D files stay 2D).
"""
from __future__ import annotations

import argparse
import sys
import warnings
from typing import List, Optional

from slam.graph import (
    G2OFormatError,
    G2OWarning,
    OptimizationResult,
    OptimizerConfig,
    Status,
    optimize,
    read_g2o,
    write_g2o,
)
from slam.graph.initialization import INITIALIZATIONS
from slam.options import check_device, positive_int
from slam.threads import limit_threads


def parse_args(argv: Optional[List[str]] = None) -> argparse.Namespace:
    defaults = OptimizerConfig()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("input", help="g2o file")
    p.add_argument("-o", "--output", default=None, help="write the optimised graph here (g2o)")
    p.add_argument("--method", choices=["lm", "gn"], default="lm",
                   help="lm = Levenberg-Marquardt (GTSAM's default), gn = Gauss-Newton (default: lm)")
    p.add_argument("--initialization", choices=INITIALIZATIONS, default="spanning_tree",
                   help="initial guess: none = the file's vertices; chordal = rotations by chordal relaxation, "
                        "then translations by least squares (GTSAM's InitializePose3; for large noise); "
                        "spanning_tree = composed along a breadth-first tree of the edges (default: spanning_tree)")
    p.add_argument("--strict", action="store_true",
                   help="refuse a file the reader would repair with a warning (an information matrix that is not "
                        "positive definite, a repeated line)")
    p.add_argument("--kernel", default=None, choices=["huber", "cauchy", "tukey", "geman_mcclure"],
                   help="robust kernel against false loop closures (default: none)")
    p.add_argument("--kernel-width", type=float, default=None, help="on sqrt(r^T Omega r); default sqrt(chi2_0.95(6))")
    p.add_argument("-n", "--max-iterations", type=int, default=defaults.max_iterations, metavar="N",
                   help=f"iteration limit (default: {defaults.max_iterations})")
    p.add_argument("--gauge", choices=["free", "first", "prior"], default=defaults.gauge,
                   help="how the graph's free rigid motion is fixed: free = left to the LM damping, then re-anchored "
                        f"on pose 0; first = pose 0 held; prior = a prior on pose 0 (default: {defaults.gauge})")
    p.add_argument("--damping", choices=["identity", "diagonal"], default=defaults.damping,
                   help="LM damping: H + lambda I (identity, GTSAM's default) or H + lambda diag(H) (diagonal) "
                        f"(default: {defaults.damping})")
    p.add_argument("--lambda-update", choices=["gtsam", "nielsen"], default=defaults.lambda_update,
                   help="how LM's lambda moves: gtsam = divided / multiplied by 10 after a good / bad step; nielsen = "
                        f"the gain-ratio rule of g2o and Ceres (default: {defaults.lambda_update})")
    p.add_argument("--solver", default="auto", choices=["auto", "sparse", "superlu", "dense", "pcg"],
                   help="linear solver of each step: sparse Cholesky, SuperLU, dense Cholesky, preconditioned "
                        "conjugate gradients; auto = dense for small systems, sparse above (default: auto)")
    p.add_argument("--threads", type=positive_int, default=1, metavar="N",
                   help="torch and BLAS threads of the optimisation (default 1; docs/devices.md)")
    p.add_argument("--device", default=None, metavar="DEV",
                   help="torch device of the graph, e.g. cuda (float64: not mps; default cpu; the torch backend)")
    p.add_argument("-v", "--verbose", action="store_true", help="one line per iteration")
    args = p.parse_args(argv)
    if args.kernel_width is not None and args.kernel is None:
        p.error("--kernel-width needs --kernel")
    if args.max_iterations < 0:
        p.error("--max-iterations must be >= 0")
    try:
        check_device(args.device, "--device", float64=True)
    except ValueError as e:
        p.error(str(e))
    return args


def summary(name: str, res: OptimizationResult) -> str:
    t = res.timings
    return (f"{name}: {res.graph.num_poses} poses, {res.graph.num_edges} edges | chi2 {res.initial_chi2:.6g} -> "
            f"{res.chi2:.6g} (GTSAM error {res.error:.6g}) | {res.iterations} iterations, {res.status} | "
            f"{t['total']:.3f} s (setup {t['setup']:.3f}, linearize {t['linearize']:.3f}, solve {t['solve']:.3f}, "
            f"evaluate {t['evaluate']:.3f})")


def main(argv: Optional[List[str]] = None) -> OptimizationResult:
    args = parse_args(argv)
    try:
        with warnings.catch_warnings(record=True) as notes:
            warnings.simplefilter("always", G2OWarning)
            graph = read_g2o(args.input, strict=args.strict)
        for note in notes:
            print(f"warning: {note.message}", file=sys.stderr)
    except (OSError, G2OFormatError) as exc:
        sys.exit(f"error: {exc}")
    if args.device is not None:
        graph = graph.to(args.device)
    with limit_threads(args.threads):  # the one thread limit of this program, around all its work
        res = optimize(graph, args.method, kernel=args.kernel, solver=args.solver, initialization=args.initialization,
                       kernel_width=args.kernel_width, max_iterations=args.max_iterations, gauge=args.gauge,
                       damping=args.damping, lambda_update=args.lambda_update, verbose=args.verbose)
    print(summary(args.input, res))
    if res.message:
        print(f"note: {res.message}")
    if args.output:
        write_g2o(args.output, res.graph)
        print(f"wrote {args.output}")
    return res


def cli() -> None:
    """Exit status 1 when the optimisation failed (solver failure, or a GN step that increased the cost)."""
    res = main()
    sys.exit(1 if res.status in (Status.SOLVER_FAILED, Status.DIVERGED) else 0)


if __name__ == "__main__":
    cli()
