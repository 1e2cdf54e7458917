"""Speed of the synthetic RGB-D generator (slam.synthetic): scene build, rendering, whole sequences.

Prints a markdown table. Timings are wall-clock and process-CPU seconds; the 1-minute load average is
printed too, because on a shared machine the wall-clock time mostly measures the other processes.

    python -m benchmarks.synthetic                 # 300 frames at 640 x 480, loop
    python -m benchmarks.synthetic --quick         # only the default settings (workers=2)
"""
from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time

import torch

from slam.synthetic import (
    build_room_scene,
    generate_sequence,
    make_trajectory,
    render_frames,
    synthetic_intrinsics,
)


def _timed(fn, *args, **kwargs):
    w, c = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - w, time.process_time() - c


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="frames of the whole-sequence runs")
    ap.add_argument("--trajectory", default="loop", help="camera trajectory of the rendered sequence")
    ap.add_argument("--render-frames", type=int, default=10, help="frames of the render-only runs")
    ap.add_argument("--quick", action="store_true",
                    help="skip the slow comparisons (torch's own threads, workers=1)")
    args = ap.parse_args()

    rows = []
    threads_before = torch.get_num_threads()
    scene, w, c = _timed(build_room_scene)
    rows.append(("build the room scene (textures + mip pyramid)", "-", f"{w:.2f}", f"{c:.2f}", "-"))
    traj = make_trajectory(args.trajectory, 300)
    n = args.render_frames
    for threads in (1, threads_before):
        torch.set_num_threads(threads)
        for width, height in ((640, 480), (160, 120)):
            K = torch.from_numpy(synthetic_intrinsics(width, height))
            render_frames(scene, K, traj.poses[:1], height, width)  # warm-up
            _, w, c = _timed(render_frames, scene, K, traj.poses[100:100 + n], height, width)
            rows.append((f"render only, {width}x{height}, torch threads={threads}", str(n), f"{w:.2f}",
                         f"{c:.2f}", f"{1e3 * w / n:.0f} ms/frame"))
        if threads == threads_before or args.quick:
            break
    torch.set_num_threads(threads_before)
    with tempfile.TemporaryDirectory() as tmp:
        for workers in ((2,) if args.quick else (2, 1)):
            _, w, c = _timed(generate_sequence, os.path.join(tmp, f"w{workers}"), args.trajectory,
                             num_frames=args.frames, scene=scene, workers=workers)
            rows.append((f"generate_sequence 640x480 + noise + PNGs, workers={workers}", str(args.frames),
                         f"{w:.1f}", f"{c:.1f}", f"{args.frames / w:.1f} frames/s"))
    print(f"torch {torch.__version__}, {os.cpu_count()} CPUs, torch threads {threads_before}, "
          f"{platform.processor() or platform.machine()}, load average (1 min) {os.getloadavg()[0]:.1f}, "
          f"{time.strftime('%Y-%m-%d')}\n")
    print("| step | frames | wall s | CPU s | rate |")
    print("|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")


if __name__ == "__main__":
    main()
