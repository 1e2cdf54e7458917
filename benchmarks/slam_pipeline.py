"""End-to-end SLAM on 7-Scenes redkitchen: ATE, loops, frames/s and time per stage, for every fusion mode.

    python benchmarks/slam_pipeline.py [--data ../shared/data] [--backbone efficientnet_lite0] [--out runs/bench_slam]

Prints (and writes to OUT/slam.md) one row per mode plus an odometry-only row, all from this one run,
and the paper's Table 1 layout (examples/ablation.py writes the same table for any list of sequences).
"""
import argparse
import json
import os
import time
from pathlib import Path

from slam.ablation import MODES, markdown_table, run_ablation
from slam.config import SLAMConfig
from slam.io import open_sequence
from slam.pipeline import evaluate_run, run_slam


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default=os.environ.get("ATTNLOOP_DATA", "../shared/data"))
    p.add_argument("--backbone", default="efficientnet_lite0")
    p.add_argument("--out", default="runs/bench_slam")
    p.add_argument("--modes", nargs="+", default=list(MODES))
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--rgb-intrinsics", nargs=4, type=float, default=None,
                   help="colour camera fx fy cx cy (7-Scenes colour: 525 525 320 240); default: registered")
    p.add_argument("--rgb-from-depth", nargs=3, type=float, default=None,
                   help="depth camera position in the colour camera, metres (7-Scenes Kinect v1: -0.025 0 0)")
    args = p.parse_args()
    seq_dir = Path(args.data) / "7scenes-redkitchen"
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    cfg = SLAMConfig()
    cfg.loop.enabled = False
    cfg.odometry.features.rgb_intrinsics = tuple(args.rgb_intrinsics) if args.rgb_intrinsics else None
    if args.rgb_from_depth:
        cfg.odometry.features.rgb_from_depth_translation = tuple(args.rgb_from_depth)
    odo = run_slam(open_sequence(seq_dir), cfg, max_frames=args.max_frames)
    odo_m = evaluate_run(odo)
    table = run_ablation([seq_dir], out, backbone=args.backbone, modes=args.modes, max_frames=args.max_frames,
                         rgb_intrinsics=args.rgb_intrinsics, rgb_from_depth=args.rgb_from_depth)

    rows = ["| run | ATE RMSE (m) | loops (true/false) | max recall @100% P before -> after verification "
            "| frames/s | odometry ms/frame | descriptor ms/keyframe | keyframes |", "|" + "---|" * 8]
    rows.append(f"| odometry only | {odo_m['ate_rmse']:.4f} | - | - | {odo_m['fps']:.1f} | "
                f"{odo_m['time_per_stage']['odometry']['ms_per_call']:.1f} | - | {odo_m['num_keyframes']} |")
    for mode in args.modes:
        m = table[mode][seq_dir.name]
        det = m.get("loop_detection", {})
        b = det.get("before_verification", {}).get("max_recall_at_full_precision", float("nan"))
        a = det.get("after_verification", {}).get("max_recall_at_full_precision", float("nan"))
        st = m["time_per_stage"]
        rows.append(f"| {args.backbone} + {mode} | {m['ate_rmse']:.4f} | {m['loops_true']}/{m['loops_false']} | "
                    f"{b:.3f} -> {a:.3f} | {m['fps']:.1f} | {st['odometry']['ms_per_call']:.1f} | "
                    f"{st.get('descriptor', {}).get('ms_per_call', float('nan')):.1f} | {m['num_keyframes']} |")
    camera = f"colour intrinsics {args.rgb_intrinsics}" if args.rgb_intrinsics else "colour/depth treated as registered"
    if args.rgb_intrinsics and args.rgb_from_depth:
        camera += f", depth camera at {args.rgb_from_depth} m in the colour camera"
    text = (f"7-Scenes redkitchen, {odo_m['num_frames']} frames, {camera}, {time.strftime('%Y-%m-%d')}\n\n"
            + "\n".join(rows) + "\n\n" + markdown_table(table))
    print(text)
    (out / "slam.md").write_text(text)
    (out / "slam.json").write_text(json.dumps({"odometry_only": odo_m, **table}, indent=2, default=float))


if __name__ == "__main__":
    main()
