"""Choosing the colour/depth baseline of an unregistered RGB-D rig without ground truth (7-Scenes redkitchen).

A Kinect v1 has two cameras: the depth (IR) camera, whose intrinsics are the frames' ``K`` (7-Scenes:
f = 585), and the colour camera (f ~ 525, centre 320, 240). With ``FeatureConfig.rgb_intrinsics`` the
depth map is warped into the colour camera before keypoints are lifted
(:mod:`slam.odometry.depth_registration`); the warp needs the depth camera's position in the colour
camera, ``FeatureConfig.rgb_from_depth_translation = (t_x, 0, 0)``, which 7-Scenes does not publish.

This script scans ``t_x``: for each value it runs the odometry alone (no loop closure; ``RGBDSLAM``
with ``loop.enabled = False``, which reports depth-camera poses when ``t_x != 0``) over the sequence and
reports

* the mean inlier RMSE (mm) and mean inlier count of the registrations that placed the frames
  (``FrameState.inlier_rmse`` / ``num_inliers``: one per tracked frame, against its keyframe): the
  selection criterion. A wrong baseline puts each keypoint's depth on a neighbouring surface point
  (parallax ``f t_x / z`` pixels), which shows as a larger 3D residual of the inliers; the criterion needs
  no ground truth, so it can choose the rig on any sequence;
* the number of keyframes and the wall seconds of the run;
* as a check only (it needs ground truth, the criterion does not): the ATE RMSE after a rigid SE(3)
  alignment, and after a Sim(3) alignment with its scale (a scale away from 1 means the lifted points are
  systematically too far or too near).

Usage::

    python benchmarks/rig_scan.py [--data ../shared/data] [--tx 0.025 0 -0.015 -0.025 -0.04]
                                  [--max-frames N] [--threads 1] [--out FILE.md]
"""
from __future__ import annotations

import argparse
import datetime
import math
import os
import platform
import shlex
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from slam.config import SLAMConfig, override
from slam.eval.metrics import ate
from slam.io import open_sequence
from slam.io.images import FrameReadError
from slam.options import KINECT_V1_RIG
from slam.system import RGBDSLAM

# Kinect v1 colour camera (fx, fy, cx, cy): the CLI's default for a 7-Scenes folder
RGB_INTRINSICS = KINECT_V1_RIG.rgb_intrinsics
DEFAULT_TX = [0.025, 0.0, -0.015, -0.025, -0.04]
HEADER = ("| t_x (m) | mean inlier RMSE (mm) | mean inliers | registrations | keyframes | lost | ATE SE3 (m) "
          "| ATE Sim3 (m) | Sim3 scale | seconds |")


def run_one(seq_dir: Path, tx: float, max_frames: int | None = None) -> dict:
    """Odometry-only run with the depth camera at ``(tx, 0, 0)`` m in the colour camera.

    Returns:
        a dict with ``tx``, ``rmse_mm``, ``inliers``, ``registrations``, ``keyframes``, ``lost``,
        ``frames``, ``ate_se3``, ``ate_sim3``, ``scale``, ``seconds`` (NaN where undefined).
    """
    cfg = SLAMConfig()
    cfg = override(cfg, {
        "loop.enabled": False,
        "odometry.features.rgb_intrinsics": RGB_INTRINSICS,
        "odometry.features.rgb_from_depth_translation": (float(tx), 0.0, 0.0)})
    seq = open_sequence(seq_dir)
    n = len(seq) if max_frames is None else min(int(max_frames), len(seq))
    view = seq[:n]
    stamps = view.timestamps
    slam = RGBDSLAM(cfg)
    t0 = time.perf_counter()
    ok = []  # FrameStates of the frames a registration placed
    for i, frame in enumerate(view.frames(on_error="yield", prefetch=2)):
        if isinstance(frame, FrameReadError):
            slam.skip(i, float(stamps[i]), str(frame))
        else:
            state = slam.track(frame)
            if math.isfinite(state.inlier_rmse):
                ok.append(state)
    result = slam.finish()
    seconds = time.perf_counter() - t0

    nan = float("nan")
    row = {
        "tx": float(tx), "frames": n, "registrations": len(ok), "keyframes": result.num_keyframes,
        "lost": result.num_lost, "seconds": seconds,
        "rmse_mm": 1000.0 * sum(r.inlier_rmse for r in ok) / len(ok) if ok else nan,
        "inliers": sum(r.num_inliers for r in ok) / len(ok) if ok else nan,
        "ate_se3": nan, "ate_sim3": nan, "scale": nan,
    }
    gt = view.groundtruth
    if gt is not None and len(gt) >= 3:
        # result.trajectory: depth-camera poses (the frame of 7-Scenes' ground truth); with loop closure
        # off it is the odometry trajectory
        a = ate(gt, result.trajectory)
        a3 = ate(gt, result.trajectory, alignment="sim3")
        row.update(ate_se3=a.rmse, ate_sim3=a3.rmse, scale=float(a3.scale))
    return row


def format_row(r: dict) -> str:
    return (f"| {r['tx']:+.3f} | {r['rmse_mm']:.2f} | {r['inliers']:.1f} | {r['registrations']} | "
            f"{r['keyframes']} | {r['lost']} | {r['ate_se3']:.4f} | {r['ate_sim3']:.4f} | {r['scale']:.4f} | "
            f"{r['seconds']:.0f} |")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default=os.environ.get("ATTNLOOP_DATA", "../shared/data"),
                   help="folder holding 7scenes-redkitchen (default $ATTNLOOP_DATA or ../shared/data)")
    p.add_argument("--tx", nargs="+", type=float, default=DEFAULT_TX,
                   help="depth camera x-positions in the colour camera, metres (default: %(default)s)")
    p.add_argument("--max-frames", type=int, default=None, help="only the first N frames (default: all)")
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (default 1; 0: torch's)")
    p.add_argument("--out", default=None, help="also write the markdown to this file")
    args = p.parse_args(argv)
    if args.max_frames is not None and args.max_frames < 3:
        p.error("--max-frames must be at least 3 (the ATE alignment needs 3 poses)")
    if any(not math.isfinite(t) for t in args.tx):
        p.error("--tx values must be finite")
    return args


def main(argv=None) -> list[dict]:
    args = parse_args(argv)
    seq_dir = Path(args.data) / "7scenes-redkitchen"
    if not (seq_dir / "frame-000000.color.jpg").is_file():
        sys.exit(f"7-Scenes redkitchen not found at {seq_dir} (set --data or ATTNLOOP_DATA)")
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    cmd = " ".join(["python", "benchmarks/rig_scan.py", *map(shlex.quote, sys.argv[1:] if argv is None
                                                              else [str(a) for a in argv])])
    machine = (f"Command: `{cmd}`, {datetime.datetime.now().strftime('%Y-%m-%d %H:%M')}, "
               f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load average "
               f"{os.getloadavg()[0]:.1f} at start, torch {torch.__version__}, {torch.get_num_threads()} "
               "torch threads.")
    setup = (f"7-Scenes redkitchen, odometry only, colour intrinsics {RGB_INTRINSICS}, depth camera at "
             "(t_x, 0, 0) m in the colour camera; inlier figures over the frame-to-keyframe "
             "registration placing a frame; ATE against the depth camera's ground truth.")
    head = [machine, "", setup, "", HEADER, "|" + "---|" * HEADER.count(" | ") + "---|"]
    print("\n".join(head), flush=True)
    rows = []
    for tx in args.tx:
        r = run_one(seq_dir, tx, args.max_frames)
        rows.append(r)
        print(format_row(r), flush=True)
    best = min(rows, key=lambda r: r["rmse_mm"] if math.isfinite(r["rmse_mm"]) else math.inf)
    tail = ["", f"{rows[0]['frames']} frames per run; lowest mean inlier RMSE at t_x = {best['tx']:+.3f} m."]
    print("\n".join(tail))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text("\n".join(head + [format_row(r) for r in rows] + tail) + "\n")
    return rows


if __name__ == "__main__":
    main()
