"""Pose-graph optimisation: slam.graph.optimize vs GTSAM 4.3 Levenberg-Marquardt, side by side.

For every g2o file in the pose-graph data folder both optimisers start from the file's VERTEX values
(the odometry initial guess, as ``gtsam.readG2o`` takes it) with default settings. The runs
alternate (GTSAM, ours, GTSAM, ...) and the median wall time of the optimisation alone
(reading excluded) is reported, one row per file. GTSAM's error is ``0.5 * chi2``; the table
reports GTSAM's error and ours (``chi2 / 2``), and GTSAM's own ``graph.error`` evaluated at our solution (the
same objective, computed by GTSAM). The CPU time (``time.process_time``) is given too: on a machine that
other processes load, it varies less than the wall time.
"s to GTSAM's error" is the wall time from the start of our call until our error was first within 1e-7
(relative) of GTSAM's final error or below it (``OptimizationResult.time_history``): where GTSAM stops
without progress (INTEL: it returns its initial guess) this, not the full run, is the comparable figure.
Peak memory is the peak resident set size of a fresh process that reads and optimises one file.
"ours ms, first call" is the untimed warm-up call on the file: it makes the sparse Cholesky's symbolic
analysis, which the timed calls find made (it is kept per sparsity pattern).

``--solvers`` prints instead, for the three files of the comparison, one damped Gauss-Newton system at the
file's vertices solved by the project's sparse Cholesky, scipy's SuperLU (minimum degree, symmetric mode) and,
when scikit-sparse is installed, CHOLMOD (its default supernodal analysis): the fastest of ``--repeats`` runs of
the symbolic analysis and of one factorisation + solve, and the largest difference to our solution.

``--starts`` prints instead, for every file, LM from the file's vertices (``initialization="none"``) against
``"auto"`` (examples/optimize_g2o.py's default: the vertices when their chi2 per edge is at most 100, else a
spanning tree of the edges): chi2, iterations, status and the median time of interleaved runs.

A robustness figure follows: sphere2500 with 5% extra edges that are random false loop closures
(seeded), optimised without a kernel and with each robust kernel; the ATE (RMSE of positions after a
rigid alignment) is taken against the solution of the clean graph.

Usage:
    python -m benchmarks.posegraph [--data DIR] [--repeats 5] [--files a b] [--no-robust] [--out FILE.md]
    python -m benchmarks.posegraph --starts [--repeats 5]
    python -m benchmarks.posegraph --solvers [--repeats 5]
"""
from __future__ import annotations

import argparse
import datetime
import importlib.metadata
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]

from slam.eval.align import umeyama_alignment
from slam.graph import PoseGraph, optimize, read_g2o
from slam.threads import limit_threads

FILES = ["tinyGrid3D", "smallGrid3D", "sphere2500", "parking-garage", "input_M3500_g2o", "input_INTEL_g2o"]


def data_dir(arg: str | None) -> Path:
    if arg:
        return Path(arg)
    return Path(os.environ.get("ATTNLOOP_DATA", ROOT.parent / "shared" / "data")) / "posegraph"


def is_3d(path: Path) -> bool:
    with open(path) as fh:
        for line in fh:
            if line.startswith("VERTEX_SE3"):
                return True
            if line.startswith("VERTEX_SE2"):
                return False
    raise ValueError(f"{path}: no vertices")


def gtsam_values(graph: PoseGraph, three_d: bool):
    """Our poses as GTSAM Values (keys = vertex ids)."""
    import gtsam

    vals = gtsam.Values()
    P = graph.poses.double().numpy()
    for key, p in zip(graph.vertex_ids.tolist(), P):
        if three_d:
            vals.insert(key, gtsam.Pose3(gtsam.Rot3.Quaternion(p[6], p[3], p[4], p[5]), gtsam.Point3(*p[:3])))
        else:
            vals.insert(key, gtsam.Pose2(p[0], p[1], 2.0 * np.arctan2(p[5], p[6])))
    return vals


def run_gtsam(path: Path, three_d: bool):
    import gtsam

    graph, initial = gtsam.readG2o(str(path), three_d)
    t, c = time.perf_counter(), time.process_time()
    opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams())
    result = opt.optimize()
    dt = time.perf_counter() - t
    return {"time": dt, "cpu": time.process_time() - c, "error": graph.error(result),
            "initial_error": graph.error(initial), "iterations": opt.iterations(), "graph": graph}


def time_to_reach(result, error: float, rtol: float = 1e-7):
    """Seconds from the start of our call until its cost (chi2 / 2) was first within ``rtol`` of GTSAM's
    final ``error`` or below it (None if never): the fair figure where GTSAM stops early, e.g. on INTEL
    where it makes no progress and returns its initial guess."""
    for cost, t in zip(result.cost_history, result.time_history):
        if cost / 2 <= error * (1 + rtol):
            return t
    return None


def ms(seconds: float) -> str:
    """Milliseconds to 3 significant digits (0.372, 25.1, 370)."""
    return f"{seconds * 1e3:.3g}"


def run_ours(graph: PoseGraph, **kw):
    t, c = time.perf_counter(), time.process_time()
    res = optimize(graph, "lm", **kw)
    return {"time": time.perf_counter() - t, "cpu": time.process_time() - c, "result": res}


def peak_rss_mb() -> float:
    """Peak resident set size of this process in MB: VmHWM (Linux; unlike ru_maxrss it is not inherited
    from the parent through fork + exec), else ru_maxrss."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def memory_probe(path: str) -> None:
    """Child process: peak RSS of reading + optimising one file (printed as JSON)."""
    base = peak_rss_mb()
    import tracemalloc

    tracemalloc.start()
    g = read_g2o(path)
    res = optimize(g, "lm")
    _, py_peak = tracemalloc.get_traced_memory()
    print(json.dumps({"baseline_mb": base, "peak_mb": peak_rss_mb(), "python_peak_mb": py_peak / 2 ** 20,
                      "status": str(res.status)}))


def measure_memory(path: Path) -> dict:
    out = subprocess.run([sys.executable, "-m", "benchmarks.posegraph", "--memory-probe", str(path)],
                         capture_output=True, text=True, check=True, cwd=ROOT)
    return json.loads(out.stdout.strip().splitlines()[-1])


def ate(a: torch.Tensor, b: torch.Tensor) -> float:
    """RMSE of positions of ``a`` after the rigid (no scale) alignment onto ``b`` (Umeyama)."""
    A, B = a[:, :3].double(), b[:, :3].double()
    R, t, _ = umeyama_alignment(A, B)
    return float((A @ R.T + t - B).pow(2).sum(-1).mean().sqrt())


def add_false_loops(graph: PoseGraph, fraction: float = 0.05, seed: int = 0) -> tuple[PoseGraph, int]:
    """Append ``fraction * E`` random false loop closures: random pose pairs more than 10 apart, a random
    rotation (uniform on SO(3)) and a translation uniform in [-5, 5]^3 m, with the information of a
    randomly chosen existing edge."""
    gen = torch.Generator().manual_seed(seed)
    n, e = graph.num_poses, graph.num_edges
    k = int(round(fraction * e))
    ii, jj = [], []
    while len(ii) < k:
        i, j = torch.randint(0, n, (2,), generator=gen).tolist()
        if abs(i - j) > 10:
            ii.append(i)
            jj.append(j)
    q = torch.nn.functional.normalize(torch.randn(k, 4, generator=gen, dtype=torch.float64), dim=-1)
    t = (torch.rand(k, 3, generator=gen, dtype=torch.float64) - 0.5) * 10.0
    info = graph.information[torch.randint(0, e, (k,), generator=gen)]
    bad = graph.clone()
    bad.add_edges(torch.tensor(ii), torch.tensor(jj), torch.cat([t, q], -1), info)
    return bad, k


def compare_solvers(folder: Path, repeats: int) -> None:
    """Symbolic analysis and one factorisation + solve of the same damped system by our sparse Cholesky,
    scipy's SuperLU and CHOLMOD (scikit-sparse, when installed); fastest of ``repeats`` runs, ms."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla

    from slam.graph import OptimizerConfig
    from slam.graph.cholesky import SymbolicCholesky
    from slam.graph.problem import TorchProblem

    try:
        from sksparse.cholmod import analyze
    except ImportError:
        analyze = None

    def fastest(f):
        out = []
        for _ in range(repeats):
            t = time.perf_counter()
            f()
            out.append(time.perf_counter() - t)
        return ms(min(out))

    print(f"Command: `python -m benchmarks.posegraph --solvers --repeats {repeats}`, load average "
          f"{os.getloadavg()[0]:.1f} at start; CHOLMOD: {'scikit-sparse' if analyze else 'not installed'}.\n")
    print("| file | unknowns | ours: analysis / factor + solve ms | SuperLU: factor + solve ms | "
          "CHOLMOD: analysis / factor + solve ms | largest difference to ours |")
    print("|---|---|---|---|---|---|")
    for name in ("sphere2500", "parking-garage", "smallGrid3D"):
        prob = TorchProblem(read_g2o(folder / f"{name}.g2o"), OptimizerConfig(), None, "free", "sparse")
        H, g = prob.linearize(prob.poses, prob.evaluate(prob.poses)[2])
        pat, k = prob.pattern, prob.pattern.k
        H = H.clone().index_add_(0, pat.diag_pos, torch.full_like(g, 1e-5))  # LM's first damping
        sym = SymbolicCholesky(pat)
        x = sym.factor(H).solve(-g).numpy()
        indptr = np.searchsorted(pat.block_rows.numpy(), np.arange(pat.num_vars + 1))
        A = sp.bsr_matrix((H.numpy().reshape(-1, k, k), pat.block_cols.numpy(), indptr),
                          shape=(pat.size, pat.size)).tocsc()
        b = -g.numpy()

        def superlu():
            return sla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                            options={"SymmetricMode": True}).solve(b)

        diffs = [np.abs(superlu() - x).max()]
        row = (f"| {name} | {pat.size} | {fastest(lambda: SymbolicCholesky(pat))} / "
               f"{fastest(lambda: sym.factor(H).solve(-g))} | {fastest(superlu)} | ")
        if analyze is None:
            row += "- | "
        else:
            F = analyze(A)
            diffs.append(np.abs(F.cholesky(A)(b) - x).max())
            row += f"{fastest(lambda: analyze(A))} / {fastest(lambda: F.cholesky(A)(b))} | "
        print(row + f"{max(diffs) / np.abs(x).max():.1e} (relative) |", flush=True)


def compare_starts(folder: Path, files, repeats: int) -> None:
    """LM from the file's vertices (the old default of examples/optimize_g2o.py) against ``"auto"`` (its
    default), runs interleaved, median CPU and wall ms."""
    when = f"{datetime.datetime.now():%Y-%m-%d %H:%M}"
    print(f"Command: `python -m benchmarks.posegraph --starts --repeats {repeats}`, {when}, {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.1f} at start.\n")
    print("| file | vertices: chi2 | iters, status | ms (CPU ms) | auto: start | chi2 | iters, status | ms (CPU ms) "
          "| time ratio (CPU) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in files:
        path = folder / f"{name}.g2o"
        if not path.exists():
            continue
        g = read_g2o(path)
        runs: dict = {"none": [], "auto": []}
        for init in ("none", "auto"):  # warm-up: imports, the symbolic analyses of both starts
            optimize(g, initialization=init)
        for _ in range(repeats):
            for init in runs:
                t, c = time.perf_counter(), time.process_time()
                res = optimize(g, initialization=init)
                runs[init].append((time.perf_counter() - t, time.process_time() - c, res))
        cells = []
        for init, rs in runs.items():
            res = rs[-1][2]
            wall, cpu = (statistics.median(r[i] for r in rs) for i in (0, 1))
            kept = res.initial_chi2 == runs["none"][-1][2].initial_chi2
            start = "" if init == "none" else ("vertices | " if kept else "tree | ")
            text = f"{start}{res.chi2:.6g} | {res.iterations}, {res.status} | {ms(wall)} ({ms(cpu)})"
            cells.append((wall, cpu, text))
        (w0, c0, a), (w1, c1, b) = cells
        print(f"| {name} | {a} | {b} | {w1 / w0:.2f} ({c1 / c0:.2f}) |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", help="folder with the g2o files (default $ATTNLOOP_DATA/posegraph)")
    ap.add_argument("--files", nargs="*", default=FILES, help="g2o files of the shared posegraph folder (default: all)")
    ap.add_argument("--repeats", type=int, default=5, help="timing repeats (the median is reported)")
    ap.add_argument("--no-robust", action="store_true", help="skip the robust-kernel runs on sphere2500")
    ap.add_argument("--no-memory", action="store_true", help="skip the memory measurements")
    ap.add_argument("--out", help="also write the markdown to this file")
    ap.add_argument("--starts", action="store_true", help="only compare the starts 'none' and 'auto' on every file")
    ap.add_argument("--solvers", action="store_true", help="only compare sparse solvers on one system per file")
    ap.add_argument("--memory-probe", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.memory_probe:
        memory_probe(args.memory_probe)
        return
    if args.starts:
        compare_starts(data_dir(args.data), args.files, args.repeats)
        return
    if args.solvers:
        compare_solvers(data_dir(args.data), args.repeats)
        return
    try:
        import gtsam  # noqa: F401
    except ImportError:
        sys.exit("GTSAM is needed for the side-by-side comparison: pip install 'attnloop[bench]'")
    folder = data_dir(args.data)
    lines = [f"Command: `python -m benchmarks.posegraph --repeats {args.repeats}`, "
             f"{datetime.datetime.now():%Y-%m-%d %H:%M}, {platform.processor() or platform.machine()}, "
             f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} at start, torch "
             f"{torch.__version__}, gtsam {importlib.metadata.version('gtsam')}.", ""]
    lines += ["| file | poses | edges | GTSAM error | ours (chi2/2) | ratio | GTSAM error at our poses "
              "| iters GTSAM / ours | GTSAM ms | ours ms | time ratio | CPU ms GTSAM / ours (ratio) "
              "| ours: ms to GTSAM's error (ratio) "
              "| ours: setup / linearize / solve / evaluate ms (medians) | ours ms, first call | peak RSS MB "
              "| status |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    # warm-up (imports, first-call allocations) outside the timings
    warm = read_g2o(folder / "tinyGrid3D.g2o") if (folder / "tinyGrid3D.g2o").exists() else None
    if warm is not None:
        optimize(warm)
    for name in args.files:
        path = folder / f"{name}.g2o"
        if not path.exists():
            print(f"skipping {path}: not found", file=sys.stderr)
            continue
        three_d = is_3d(path)
        g = read_g2o(path)
        gt_runs, our_runs = [], []
        run_gtsam(path, three_d)
        first = run_ours(g)["time"]
        for _ in range(args.repeats):
            gt_runs.append(run_gtsam(path, three_d))
            our_runs.append(run_ours(g))
        gt = gt_runs[-1]
        t_gt = statistics.median(r["time"] for r in gt_runs)
        ours = our_runs[-1]["result"]
        t_ours = statistics.median(r["time"] for r in our_runs)
        c_gt, c_ours = (statistics.median(r["cpu"] for r in runs) for runs in (gt_runs, our_runs))
        reach = [time_to_reach(r["result"], gt["error"]) for r in our_runs]
        t_reach = statistics.median(reach) if None not in reach else None
        reach_txt = "not reached" if t_reach is None else f"{ms(t_reach)} ({t_reach / t_gt:.2f})"
        err_ours = ours.chi2 / 2
        gt_at_ours = gt["graph"].error(gtsam_values(ours.graph, three_d))
        # the median of each stage over the runs (one run's split is noisy at sub-millisecond scale)
        tm = {k: statistics.median(r["result"].timings[k] for r in our_runs) for k in ours.timings}
        mem = {} if args.no_memory else measure_memory(path)
        row = (f"| {name} | {g.num_poses} | {g.num_edges} | {gt['error']:.6f} | {err_ours:.6f} | "
               f"{err_ours / gt['error']:.7f} | {gt_at_ours:.6f} | {gt['iterations']} / {ours.iterations} | "
               f"{ms(t_gt)} | {ms(t_ours)} | {t_ours / t_gt:.2f} | {ms(c_gt)} / {ms(c_ours)} ({c_ours / c_gt:.2f}) | "
               f"{reach_txt} | "
               f"{' / '.join(ms(tm[k]) for k in ('setup', 'linearize', 'solve', 'evaluate'))} | {ms(first)} | "
               f"{mem.get('peak_mb', float('nan')):.0f} | "
               f"{ours.status} |")
        lines.append(row)
        print(row, flush=True)
    intel = folder / "input_INTEL_g2o.g2o"
    if "input_INTEL_g2o" in args.files and intel.exists():
        # GTSAM stops at its first linearisation on this file (indeterminate system); our LM from the file's
        # vertices (raw odometry) is still descending after 100 iterations. Marquardt's scaled damping
        # converges in hundreds, Nielsen's gain-ratio rule (g2o, Ceres) lower than the x2 / /2 schedule; a
        # start composed along a spanning tree of the edges or the
        # chordal one converges in a few, lower still ("auto", examples/optimize_g2o.py's default, takes the tree
        # here: the vertices' chi2 is ~4500 per edge).
        g = read_g2o(intel)
        lines.append("")
        for kw in ({"damping": "diagonal", "lambda_factor": 2.0}, {"damping": "diagonal", "lambda_update": "nielsen"},
                   {"initialization": "spanning_tree"}, {"initialization": "chordal"}):
            t = time.perf_counter()
            res = optimize(g, "lm", max_iterations=1000, **kw)
            how = ", ".join(f"{k}={v!r}" for k, v in kw.items())
            lines.append(f"input_INTEL_g2o with `{how}, max_iterations=1000`: chi2/2 = "
                         f"{res.chi2 / 2:.4f} after {res.iterations} iterations ({res.status}), "
                         f"{time.perf_counter() - t:.1f} s.")
            print(lines[-1], flush=True)
    if not args.no_memory:
        base = measure_memory(folder / "tinyGrid3D.g2o")["baseline_mb"]
        lines += ["", "Peak RSS (VmHWM) is that of a fresh process reading and optimising the file, python + "
                  f"torch + numpy/scipy imports included (~{base:.0f} MB before reading)."]
    if not args.no_robust and (folder / "sphere2500.g2o").exists():
        g = read_g2o(folder / "sphere2500.g2o")
        clean = optimize(g)
        bad, k = add_false_loops(g)
        P = clean.graph.poses[:, :3]
        extent = float((P.amax(0) - P.amin(0)).norm())
        lines += ["", f"Robustness: sphere2500 + {k} random false loop closures "
                      f"(5% of {g.num_edges}, seed 0; "
                      f"trajectory extent {extent:.1f} m). ATE = RMSE of positions vs the clean solution "
                      "after rigid alignment.", "",
                  "| kernel (width on sqrt(r^T Omega r)) | ATE vs clean (m) | mean weight of false edges | "
                  "true edges with weight < 0.5 | iterations | status | time s |",
                  "|---|---|---|---|---|---|---|"]
        for kern in [None, "huber", "cauchy", "tukey", "geman_mcclure"]:
            t = time.perf_counter()
            res = optimize(bad, "lm", kernel=kern)
            dt = time.perf_counter() - t
            w = res.weights
            row = (f"| {kern or 'none'} | {ate(res.graph.poses, clean.graph.poses):.4f} | "
                   f"{float(w[g.num_edges:].mean()):.2e} | {int((w[:g.num_edges] < 0.5).sum())} | "
                   f"{res.iterations} | {res.status} | {dt:.1f} |")
            lines.append(row)
            print(row, flush=True)
    # the machine may be shared: the load at the end beside the one at the start says how steady it was
    lines[0] = lines[0].replace(" at start,", f" at start, {os.getloadavg()[0]:.1f} at end,")
    text = "\n".join(lines)
    print()
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")


if __name__ == "__main__":
    with limit_threads(1):  # torch's and BLAS's pools: the work is many small operations (docs/devices.md)
        main()
