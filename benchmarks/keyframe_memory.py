"""What a run keeps per keyframe, in bytes: the odometry's keyframe (features, image), the loop index's
descriptor, the map's points, the pose graph's entry. Array payloads only (numpy / torch ``nbytes``), not the
Python objects around them.

    OMP_NUM_THREADS=1 python -m benchmarks.keyframe_memory /work/shared/data/7scenes-redkitchen --frames 0:300
    OMP_NUM_THREADS=1 python -m benchmarks.keyframe_memory --demo-frames 600      # the built-in building scene
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch


def _nbytes(x) -> int:
    if x is None:
        return 0
    if isinstance(x, torch.Tensor):
        return x.numel() * x.element_size()
    if isinstance(x, np.ndarray):
        return int(x.nbytes)
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sequence", nargs="?", default=None, help="a sequence folder (default: the building demo)")
    p.add_argument("--frames", default=None, help="START:END of the sequence")
    p.add_argument("--demo-frames", type=int, default=600, help="frames of the building demo without a sequence")
    p.add_argument("--save-map", action="store_true", help="run as with --save-map (keyframe images kept)")
    args = p.parse_args(argv)

    from slam import pipeline
    from slam.io import open_sequence
    from slam.options import frame_range, resolve_settings

    tmp = Path(tempfile.mkdtemp())
    if args.sequence is None:
        from slam.synthetic.demo import generate_demo

        folder = generate_demo(tmp / "demo", scene="building", num_frames=args.demo_frames)
        seq = open_sequence(folder)
    else:
        seq = open_sequence(args.sequence)
    cfg = resolve_settings(None, None, seq).config
    captured = {}

    class Spy(pipeline.RGBDSLAM):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            captured["slam"] = self

    pipeline.RGBDSLAM = Spy
    run = pipeline.run_slam(seq, cfg, progress=False, frames=frame_range(args.frames) if args.frames else None,
                            save_map=tmp / "map" if args.save_map else None)
    slam = captured["slam"]
    kfs = slam.keyframes
    M = len(kfs)
    feats = {name: sum(_nbytes(getattr(kf.features, name)) for kf in kfs if kf.features is not None) / M
             for name in ("keypoints", "descriptors", "points", "valid", "sigma_px", "K")}
    n_kp = sum(len(kf.features) for kf in kfs if kf.features is not None) / M
    rgb = sum(_nbytes(kf.rgb) for kf in kfs) / M
    index = slam.loop_closer.detector.index
    desc = index.dim * 4 if len(index) else 0
    cloud = run.map
    graph = sum(_nbytes(t) for t in (slam.graph.estimates(), slam.graph.odometry_poses())) / M + \
        sum(_nbytes(e.T_ij) + _nbytes(e.information) for e in slam.graph.edges) / M
    print(f"{seq.name}: {run.result.num_frames} frames, {M} keyframes, {len(run.result.loops)} loops; "
          "bytes per keyframe:")
    print(f"  features: {sum(feats.values()):,.0f} ({n_kp:.0f} keypoints: " +
          ", ".join(f"{k} {v:,.0f}" for k, v in feats.items()) + ")")
    print(f"  image (Keyframe.rgb): {rgb:,.0f}" + (" (kept for the saved map)" if args.save_map else ""))
    print(f"  loop index descriptor: {desc:,} ({index.dim} float32)")
    if cloud is not None:
        print(f"  map points: {cloud.nbytes / M:,.0f} ({cloud.num_points / M:,.0f} points of 9 bytes)")
    print(f"  pose graph (estimate, odometry pose, edges' T and information): {graph:,.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
