"""How far odometry drifts per metre travelled between revisited keyframes: the data behind the drift bound.

    python benchmarks/loop_drift_bound.py [--data ../shared/data] [--building DIR] [--steps 1 3 6]

For each sequence (redkitchen at each frame step, and the building tour when ``--building`` names its
generated folder) an odometry-only run; then for every pair of keyframes that ground truth puts within
the verification's reach (< 0.4 m, < 40 deg) and at least 3 s apart, the disagreement between the
odometry's relative pose and the true one, against the distance travelled between them along the odometry
chain. Prints per sequence the quantiles of the disagreement and of disagreement / distance, and the
fraction of pairs the default bound (``DriftBoundConfig``) admits, and the same for the old fixed bound
(0.3 m / 20 deg).
"""
import argparse
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

from slam.config import SLAMConfig, override
from slam.io import open_sequence
from slam.lie import se3_between, so3_log
from slam.loop.acceptance import DriftBoundConfig, drift_limits
from slam.pipeline import run_slam


def pairs_of(run, min_gap_s=3.0):
    res = run.result
    frames = res.keyframe_frames.numpy()
    gt = run.gt_poses_per_frame[frames]
    odo = res.odometry_trajectory.poses[frames]
    stamps = res.keyframe_trajectory.timestamps.numpy()
    steps = torch.diff(odo[:, :3], dim=0).norm(dim=1).numpy()
    travelled = np.concatenate([[0.0], np.cumsum(steps)])
    out = []
    n = len(frames)
    for b in range(n):
        for a in range(b):
            if stamps[b] - stamps[a] < min_gap_s or not torch.isfinite(gt[a]).all() or not torch.isfinite(gt[b]).all():
                continue
            rel = se3_between(gt[a], gt[b])
            if float(rel[:3].norm()) > 0.4 or math.degrees(float(so3_log(rel[3:]).norm())) > 40:
                continue
            err = se3_between(se3_between(odo[a], odo[b]), rel)
            out.append((travelled[b] - travelled[a], float(err[:3].norm()),
                        math.degrees(float(so3_log(err[3:]).norm()))))
    return np.array(out).reshape(-1, 3)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default=os.environ.get("ATTNLOOP_DATA", "../shared/data"), help="the shared data folder (default: ATTNLOOP_DATA or ../shared/data)")
    p.add_argument("--building", default=None, help="a generated building sequence folder (attnloop-slam --demo "
                   "--demo-scene building writes one into OUT/demo_sequence)")
    p.add_argument("--steps", nargs="+", type=int, default=[1, 3, 6], help="frame steps to run the kitchen at")
    args = p.parse_args()
    torch.set_num_threads(1)
    seqs = []
    kitchen = Path(args.data) / "7scenes-redkitchen"
    if kitchen.is_dir():
        for step in args.steps:
            seqs.append((f"redkitchen step {step}", open_sequence(kitchen)[::step], True))
    if args.building:
        seqs.append(("building", open_sequence(args.building), False))
    bound = DriftBoundConfig()
    print(f"# {time.strftime('%Y-%m-%d %H:%M')}, DriftBoundConfig() = {bound}")
    print("| sequence | pairs | travelled m (median, max) | drift m (median, p95, max) | drift deg (median, p95, max) "
          "| rate needed above the default bases (m/m, deg/m) | admitted: drift bound | admitted: fixed 0.3 m / 20 deg |")
    print("|" + "---|" * 8)
    for name, seq, rig in seqs:
        cfg = SLAMConfig()
        cfg = override(cfg, {"loop.enabled": False})
        if rig:
            cfg = override(cfg, {
                "odometry.features.rgb_intrinsics": (525.0, 525.0, 320.0, 240.0),
                "odometry.features.rgb_from_depth_translation": (-0.025, 0.0, 0.0)})
        run = run_slam(seq, cfg, progress=False)
        d = pairs_of(run)
        if not len(d):
            print(f"| {name} | 0 | - | - | - | - | - | - | - |")
            continue
        L, t, r = d[:, 0], d[:, 1], d[:, 2]
        lim = np.array([drift_limits(x, bound) for x in L])
        ok = ((t <= lim[:, 0]) & (r <= lim[:, 1])).mean()
        fixed = ((t <= 0.3) & (r <= 20.0)).mean()
        Lp = np.maximum(L, 1e-3)
        q = np.quantile
        # the smallest growth rates that admit every pair, given the default bases
        rate_t = max(0.0, float(((t - bound.translation_base) / Lp).max()))
        rate_r = max(0.0, float(((r - bound.rotation_base_deg) / Lp).max()))
        print(f"| {name} | {len(d)} | {np.median(L):.1f}, {L.max():.1f} | {np.median(t):.3f}, {q(t, .95):.3f}, "
              f"{t.max():.3f} | {np.median(r):.2f}, {q(r, .95):.2f}, {r.max():.2f} | {rate_t:.4f}, {rate_r:.3f} "
              f"| {ok:.3f} | {fixed:.3f} |", flush=True)


if __name__ == "__main__":
    main()
