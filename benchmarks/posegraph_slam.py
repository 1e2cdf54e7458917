"""Does the pose-graph accelerator matter in the SLAM pipeline? Every optimisation of a real run, replayed with
each backend.

1. Runs the SLAM pipeline on 7-Scenes redkitchen (the README's main command: colour intrinsics
   525 525 320 240, depth camera at -0.025 0 0, EfficientNet-Lite0 + DAM) and captures every call the back
   end (``slam.backend``) makes to ``slam.graph.optimize``: the online corrections after accepted loops and the
   final optimisation, each with its graph and settings (kernels included).
2. Replays them with the torch backend and the accelerator (numpy functions, C kernels): one round is every
   call once with one backend; rounds alternate between the backends; medians of ``--repeats`` rounds.
3. Reports the total per backend against the run's wall time, and the final call alone.

``--save FILE.g2o`` also writes the last graph (without its kernels) for other uses.

Usage:
    python benchmarks/posegraph_slam.py [--data ../shared/data] [--max-frames N] [--repeats 7] [--save FILE]
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

import slam.backend  # noqa: E402  (after the sys.path line)
from slam.config import SLAMConfig, override  # noqa: E402
from slam.graph import compiled_kernels, optimize, write_g2o  # noqa: E402


def capture_run(data: Path, max_frames, backbone: str):
    """Run the pipeline; returns (calls [(graph, args, kwargs)], wall seconds of the run, frames)."""
    from slam.io import open_sequence
    from slam.pipeline import run_slam

    cfg = SLAMConfig()
    cfg = override(cfg, {
        "loop.descriptor.backbone": backbone,
        "loop.descriptor.fusion": "dam",
        "odometry.features.rgb_intrinsics": (525.0, 525.0, 320.0, 240.0),
        "odometry.features.rgb_from_depth_translation": (-0.025, 0.0, 0.0)})
    calls = []
    real = slam.backend.optimize

    def spy(graph, *args, **kwargs):
        calls.append((graph.clone(), args, dict(kwargs)))
        return real(graph, *args, **kwargs)

    slam.backend.optimize = spy
    try:
        run = run_slam(open_sequence(data / "7scenes-redkitchen"), cfg, max_frames=max_frames, progress=False)
    finally:
        slam.backend.optimize = real
    if not calls:
        sys.exit("the run made no pose-graph optimisation (no loop closure was accepted)")
    return calls, run.wall_seconds, run.result.num_frames


def replay(calls, backend: str) -> float:
    """Seconds to make every captured call once with ``backend``."""
    t = time.perf_counter()
    for graph, args, kwargs in calls:
        optimize(graph, *args, backend=backend, **kwargs)
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=os.environ.get("ATTNLOOP_DATA", str(ROOT.parent / "shared" / "data")), help="the shared data folder (default: ATTNLOOP_DATA or ../shared/data)")
    ap.add_argument("--save", default=None, help="write the last captured graph here (g2o, without kernels)")
    ap.add_argument("--max-frames", type=int, default=None, help="kitchen frames to run (default: all)")
    ap.add_argument("--backbone", default="efficientnet_lite0", help="descriptor backbone")
    ap.add_argument("--repeats", type=int, default=7, help="replays of every optimisation (the median is reported)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    load = os.getloadavg()[0]
    calls, run_s, frames = capture_run(Path(args.data), args.max_frames, args.backbone)
    if args.save:
        write_g2o(args.save, calls[-1][0])
    backends = ("torch", "numpy", "c") if compiled_kernels() else ("torch", "numpy")
    last = calls[-1:]
    totals = {b: [] for b in backends}
    finals = {b: [] for b in backends}
    for b in backends:  # warm-up
        replay(calls, b)
    for _ in range(args.repeats):
        for b in backends:
            totals[b].append(replay(calls, b))
            finals[b].append(replay(last, b))
    sizes = [g.num_poses for g, _, _ in calls]
    g_last = calls[-1][0]
    loops = int(((g_last.ii - g_last.jj).abs() > 1).sum())
    results = {b: optimize(g_last, *calls[-1][1], backend=b, **calls[-1][2]) for b in backends}
    lines = [f"Command: `python benchmarks/posegraph_slam.py --repeats {args.repeats}`, "
             f"{datetime.datetime.now():%Y-%m-%d %H:%M}, {os.cpu_count()} CPUs, load average {load:.1f} at the "
             f"start of the run, {os.getloadavg()[0]:.1f} after it, torch {torch.__version__}.", "",
             f"Run: {frames} frames in {run_s:.1f} s wall; the back end made {len(calls)} optimize calls on graphs "
             f"of {min(sizes)}-{max(sizes)} keyframes; the last graph has {g_last.num_poses} poses, "
             f"{g_last.num_edges} edges ({loops} not between consecutive keyframes).", "",
             "| backend | all calls ms (median; min-max) | share of the run | last call ms | last call chi2/2 | "
             "iterations |", "|---|---|---|---|---|---|"]
    for b in backends:
        t = totals[b]
        med = statistics.median(t)
        r = results[b]
        lines.append(f"| {b} | {1e3 * med:.1f} ({1e3 * min(t):.1f}-{1e3 * max(t):.1f}) | {med / run_s:.2%} | "
                     f"{1e3 * statistics.median(finals[b]):.2f} | {r.chi2 / 2:.6f} | {r.iterations} |")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
