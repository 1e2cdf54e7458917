"""Cost of reading RGB-D frames (slam.io) and of the evaluation functions (slam.eval).

Frame reading: on the shared 7-Scenes redkitchen sequence (640x480 JPEG colour + 16-bit PNG depth),
per frame: colour decode, depth decode, a whole ``seq[i]`` (decode + BGR->RGB + depth to metres +
ground-truth pose), and passes over the frames with ``seq.frames(prefetch=k)``, the caller doing no
work (reading throughput) or sleeping ``--work-ms`` per frame (a stand-in for GIL-free compute: with
prefetching the reading should hide behind it). Files are read once before timing, so the OS cache is warm
(a cold first pass adds the disk). Evaluation: ATE / RPE of a 1000-pose trajectory, TUM association of
two 10^4-stamp streams, ground-truth loop pairs of the 1000 redkitchen poses.

Usage:
    python -m benchmarks.io_read                 # 300 frames
    python -m benchmarks.io_read --frames 1000
    ATTNLOOP_DATA=/path/to/data python -m benchmarks.io_read

Prints markdown tables. "min" approximates the cost on an idle machine (other processes only add
time); median/mean/p90 show what a shared machine gives.
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks._common import add_data_argument
from slam.eval import LoopGroundTruthConfig, associate, ate, ground_truth_loops, rpe
from slam.io import RGBDFrame, Trajectory, check_frame, open_sequence, read_depth_raw, read_rgb
from slam.lie import se3_compose, se3_exp


def _times(fn, items, repeat=1):
    out = []
    for _ in range(repeat):
        for it in items:
            t0 = time.perf_counter()
            fn(it)
            out.append((time.perf_counter() - t0) * 1e3)
    return out


def _row(name, ms):
    ms = sorted(ms)
    p90 = ms[min(len(ms) - 1, int(0.9 * len(ms)))]
    return (f"| {name} | {ms[0]:.2f} | {statistics.median(ms):.2f} | {statistics.fmean(ms):.2f} | {p90:.2f} | "
            f"{len(ms)} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=300, help="frames read per variant")
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    ap.add_argument("--work-ms", type=float, default=20.0, help="simulated per-frame work of the caller")
    add_data_argument(ap)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    seq = open_sequence(Path(args.data) / "7scenes-redkitchen")
    n = min(args.frames, len(seq))
    idx = list(range(n))
    for i in idx:  # warm the OS file cache
        for p in seq.paths(i):
            p.read_bytes()
    seq.groundtruth  # noqa: B018  (reads the pose files once; frames then take poses from memory)

    print(f"# slam.io / slam.eval timings ({time.strftime('%Y-%m-%d')}, {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs, torch {torch.__version__}, {torch.get_num_threads()} threads)\n")
    print(f"Frames: 7scenes-redkitchen 0..{n - 1}, 640x480, warm file cache.\n")
    print("| step | min ms | median ms | mean ms | p90 ms | samples |")
    print("|---|---|---|---|---|---|")
    print(_row("colour JPEG decode + RGB", _times(lambda i: read_rgb(str(seq.paths(i)[0])), idx)))
    print(_row("depth 16-bit PNG decode", _times(lambda i: read_depth_raw(str(seq.paths(i)[1])), idx)))
    print(_row("`seq[i]` (whole frame)", _times(lambda i: seq[i], idx)))
    # the checks of RGBDFrame (slam.io.frame.check_frame): alone, and seq[i] with / without them,
    # interleaved frame by frame so that both see the same load
    frame = seq[0]
    print(_row("`check_frame` (the RGBDFrame checks alone)", _times(lambda _: check_frame(frame), idx)))
    checked, unchecked, post_init = [], [], RGBDFrame.__post_init__
    for i in idx:
        for out, hook in ((checked, post_init), (unchecked, lambda self: None)):
            RGBDFrame.__post_init__ = hook
            t0 = time.perf_counter()
            seq[i]
            out.append((time.perf_counter() - t0) * 1e3)
    RGBDFrame.__post_init__ = post_init
    print(_row("`seq[i]`, frame checks on (interleaved)", checked))
    print(_row("`seq[i]`, frame checks off (interleaved)", unchecked))
    for work in (0.0, args.work_ms):
        for k in (0, 1, 2):
            t0 = time.perf_counter()
            count = 0
            for _ in seq[:n].frames(prefetch=k):
                count += 1
                if work:
                    time.sleep(work / 1e3)  # stands for the caller's GIL-free work (torch, OpenCV)
            per = (time.perf_counter() - t0) * 1e3 / count
            what = f"`frames(prefetch={k})`, caller works {work:g} ms/frame: per frame"
            print(f"| {what} | - | {per:.2f} | {per:.2f} | - | {count} |")

    gt = seq.groundtruth
    g = torch.Generator().manual_seed(0)
    noise = torch.randn(len(gt), 6, generator=g, dtype=torch.float64) * 0.01
    est = Trajectory(gt.timestamps, se3_compose(gt.poses, se3_exp(noise)))
    stamps_a = np.cumsum(np.full(10_000, 1 / 30)) + np.random.default_rng(0).normal(0, 0.002, 10_000)
    stamps_b = np.cumsum(np.full(10_000, 1 / 30)) + 0.005
    cfg = LoopGroundTruthConfig()
    print("\n| evaluation | min ms | median ms | mean ms | p90 ms | samples |")
    print("|---|---|---|---|---|---|")
    print(_row(f"`ate` ({len(gt)} poses, SE(3) alignment)", _times(lambda _: ate(gt, est), range(5))))
    print(_row(f"`rpe` ({len(gt)} poses, delta 1 frame)", _times(lambda _: rpe(gt, est), range(5))))
    print(_row("`rpe` (delta 1 s, all pairs)", _times(lambda _: rpe(gt, est, 1.0, "seconds", True), range(5))))
    print(_row("`associate` (10^4 x 10^4 stamps)", _times(lambda _: associate(stamps_a, stamps_b), range(3))))
    print(_row(f"`ground_truth_loops` ({len(gt)} poses)", _times(lambda _: ground_truth_loops(gt.poses, cfg),
                                                                  range(3))))


if __name__ == "__main__":
    main()
