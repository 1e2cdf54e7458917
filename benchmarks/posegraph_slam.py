"""Does the pose-graph accelerator matter in the SLAM pipeline? The keyframe graph of a real run, optimised
with each backend.

1. Runs the SLAM pipeline on 7-Scenes redkitchen (the README's main command: colour intrinsics
   525 525 320 240, depth camera at -0.025 0 0, EfficientNet-Lite0 + DAM) and captures the pose graph and
   the settings ``slam.system`` passes to ``optimize`` (or reads a graph saved by an earlier run:
   ``--graph FILE.g2o``; the settings are then the pipeline's defaults, ``SLAMConfig().backend``).
2. Times that optimisation with the torch backend and the accelerator (numpy functions, C kernels),
   interleaved, median of ``--repeats``, and reports its share of the run's wall time.
3. Times the optimisations ``BackendConfig.optimize_on_loop`` would add: at each loop closure (in the
   order of its later keyframe) the graph of the keyframes so far, summed over the run.

Usage:
    python benchmarks/posegraph_slam.py [--data ../shared/data] [--graph FILE.g2o] [--save FILE.g2o]
                                        [--max-frames N] [--repeats 15]
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

import slam.system  # noqa: E402  (after the sys.path line)
from slam.config import SLAMConfig  # noqa: E402
from slam.graph import PoseGraph, compiled_kernels, optimize, read_g2o, write_g2o  # noqa: E402


def capture_run(data: Path, max_frames, backbone: str):
    """Run the pipeline; returns (graph, optimize kwargs, wall seconds of the run, frames)."""
    from slam.io import open_sequence
    from slam.pipeline import run_slam

    cfg = SLAMConfig()
    cfg.loop.descriptor.backbone = backbone
    cfg.loop.descriptor.fusion = "dam"
    cfg.odometry.features.rgb_intrinsics = (525.0, 525.0, 320.0, 240.0)
    cfg.odometry.features.rgb_from_depth_translation = (-0.025, 0.0, 0.0)
    calls = []
    real = slam.system.optimize

    def spy(graph, *args, **kwargs):
        calls.append((graph.clone(), args, dict(kwargs)))
        return real(graph, *args, **kwargs)

    slam.system.optimize = spy
    try:
        run = run_slam(open_sequence(data / "7scenes-redkitchen"), cfg, max_frames=max_frames, progress=False)
    finally:
        slam.system.optimize = real
    if not calls:
        sys.exit("the run made no pose-graph optimisation (no loop closure was accepted)")
    graph, args, kwargs = calls[-1]
    if args:
        kwargs = dict(zip(("method", "kernel"), args), **kwargs)
    return graph, kwargs, run.wall_seconds, run.result.num_frames


def median_ms(fns: dict, repeats: int) -> dict:
    """Median ms of each callable, interleaved (A, B, C, A, B, C, ...) after one warm-up call each."""
    for fn in fns.values():
        fn()
    times = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t)
    return {k: (1e3 * statistics.median(v), 1e3 * min(v), 1e3 * max(v)) for k, v in times.items()}


def prefix(graph: PoseGraph, n: int) -> PoseGraph:
    keep = (graph.ii < n) & (graph.jj < n)
    return PoseGraph(graph.poses[:n], graph.ii[keep], graph.jj[keep], graph.measurements[keep],
                     graph.information[keep])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=os.environ.get("ATTNLOOP_DATA", str(ROOT.parent / "shared" / "data")))
    ap.add_argument("--graph", default=None, help="a keyframe graph saved by --save (skips the SLAM run)")
    ap.add_argument("--save", default=None, help="write the captured keyframe graph here (g2o)")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--backbone", default="efficientnet_lite0")
    ap.add_argument("--repeats", type=int, default=15)
    args = ap.parse_args()
    torch.set_num_threads(1)
    if args.graph:
        graph, run_s, frames = read_g2o(args.graph), None, None
        b = SLAMConfig().backend
        kwargs = dict(method=b.method, kernel=b.kernel, kernel_width=b.kernel_width, max_iterations=b.max_iterations)
    else:
        graph, kwargs, run_s, frames = capture_run(Path(args.data), args.max_frames, args.backbone)
        if args.save:
            write_g2o(args.save, graph)
    backends = ("torch", "numpy", "c") if compiled_kernels() else ("torch", "numpy")
    source = f"`--graph {args.graph}`" if args.graph else (
        f"captured from a run of {frames} frames ({run_s:.1f} s wall)")
    loops = int(((graph.ii - graph.jj).abs() > 1).sum())
    lines = [f"Command: `python benchmarks/posegraph_slam.py --repeats {args.repeats}"
             + (f" --graph {args.graph}" if args.graph else "") + f"`, {datetime.datetime.now():%Y-%m-%d %H:%M}, "
             f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} at start, torch {torch.__version__}.",
             "", f"Keyframe graph {source}: {graph.num_poses} poses, {graph.num_edges} edges ({loops} loop "
             f"closures); optimize settings {kwargs}.", ""]
    results = {b: optimize(graph, backend=b, **kwargs) for b in backends}
    ms = median_ms({b: (lambda b=b: optimize(graph, backend=b, **kwargs)) for b in backends}, args.repeats)
    lines += ["| backend | ms (median; min-max) | share of the run | chi2/2 | iterations | status |",
              "|---|---|---|---|---|---|"]
    for b in backends:
        share = f"{ms[b][0] / 1e3 / run_s:.2%}" if run_s else "-"
        r = results[b]
        lines.append(f"| {b} | {ms[b][0]:.2f} ({ms[b][1]:.2f}-{ms[b][2]:.2f}) | {share} | {r.chi2 / 2:.6f} | "
                     f"{r.iterations} | {r.status} |")
    # what optimising at every loop closure would add: the graph of the keyframes so far at each loop
    ends = sorted({int(max(i, j)) + 1 for i, j in zip(graph.ii.tolist(), graph.jj.tolist()) if abs(i - j) > 1})
    subs = [prefix(graph, n) for n in ends]
    total = {}
    for b in backends:
        fns = {k: (lambda s=s, b=b: optimize(s, backend=b, **kwargs)) for k, s in enumerate(subs)}
        per = median_ms(fns, max(3, args.repeats // 3))
        total[b] = sum(v[0] for v in per.values())
    lines += ["", f"Optimising at each of the {len(subs)} loop closures (graphs of {subs[0].num_poses}-"
              f"{subs[-1].num_poses} keyframes), summed over the run: "
              + ", ".join(f"{b} {total[b]:.0f} ms" for b in backends)
              + (f" ({total['torch'] / 1e3 / run_s:.1%} of the run with torch)." if run_s else ".")]
    text = "\n".join(lines)
    print(text)


if __name__ == "__main__":
    main()
