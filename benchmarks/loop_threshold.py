"""Which adaptive-threshold settings the default descriptor needs in the SLAM loop detector.

The kitchen (7-Scenes redkitchen) as a keyframe stream: every ``--step``-th frame is a keyframe, fed in
order to :class:`attnloop.index.LoopCandidateDetector` (exclusion window ``100 / step`` keyframes, i.e.
100 frames, as the loop ground truth's frame gap). For each :class:`attnloop.threshold.ThresholdConfig`
the accepted best candidates are labelled by the poses (0.5 m, 45 degrees): precision, recall (over the
keyframes that have a true earlier match) and the number of false accepts, for the default descriptor
and for ``preset="paper"``, fusion ``dam``. Recall at 100 % precision of the raw top-1 similarity is
given for reference (the best any single similarity threshold can do).

Usage:
    python benchmarks/loop_threshold.py [--data ../shared/data] [--step 5]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from place_recognition import data_root, kitchen_poses, load_rgb

from attnloop import AttentionDescriptor
from attnloop.index import LoopCandidateDetector, LoopDetectorConfig
from attnloop.threshold import ThresholdConfig
from slam.eval.loops import LoopGroundTruthConfig
from slam.eval.place_recognition import evaluate, ground_truth_from_poses, sequence_candidates

# (method, k_sigma, min_margin, min_similarity)
SETTINGS = ([("mad", k, 0.02, 0.0) for k in (1.5, 2.0, 3.0, 4.0)] + [("std", 3.0, 0.02, 0.0)]
            + [("mad", k, 0.005, 0.0) for k in (1.0, 1.5, 2.0)]
            + [("mad", 1.0, 0.005, f) for f in (0.90, 0.93, 0.95)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=data_root(), help="the shared data folder (default: ATTNLOOP_DATA or ../shared/data)")
    parser.add_argument("--step", type=int, default=5, help="every STEP-th kitchen frame is a keyframe")
    parser.add_argument("--presets", nargs="+", default=["default", "paper"], choices=["default", "paper"], help="descriptor presets to compare")
    args = parser.parse_args()
    torch.set_num_threads(1)
    seq = args.data / "7scenes-redkitchen"
    frames = list(range(0, 1000, args.step))
    images = [torch.from_numpy(load_rgb(seq / f"frame-{i:06d}.color.jpg")).permute(2, 0, 1) for i in frames]
    gap = 100 // args.step
    gt = ground_truth_from_poses(kitchen_poses(seq, frames), config=LoopGroundTruthConfig(0.5, 45.0, gap))
    has = gt.any(1)
    print(f"# Loop-detector thresholds on the kitchen stream ({time.strftime('%Y-%m-%d %H:%M')}): {len(frames)} "
          f"keyframes (every {args.step}th frame), window {gap}, {int(has.sum())} with a true earlier match\n")
    print("| descriptor | threshold | accepted | precision | recall | false accepts |\n|---|---|---|---|---|---|")
    for label, preset in [(f"{p} dam", None if p == "default" else p) for p in args.presets]:
        desc = AttentionDescriptor("efficientnet_lite0", fusion="dam", pretrained=True, preset=preset)
        with torch.no_grad():
            d = torch.cat([desc(torch.stack(images[s:s + 8])) for s in range(0, len(images), 8)])
        r = evaluate(d @ d.T, gt, candidates=sequence_candidates(len(frames), gap))
        print(f"| {label} | top-1 similarity at 100 % precision: {r.threshold_at_full_precision:.3f} | - | 1.000 | "
              f"{r.recall_at_full_precision:.3f} | 0 |")
        for method, k, margin, floor in SETTINGS:
            cfg = LoopDetectorConfig(window=gap, threshold=ThresholdConfig(method=method, k_sigma=k, min_margin=margin,
                                                                           min_similarity=floor, min_samples=16),
                                     threshold_samples=4096)
            det = LoopCandidateDetector(cfg)
            tp = fp = 0
            for i in range(len(frames)):
                out = det.add_and_query(d[i], keyframe_id=i)
                if out.ids.numel():
                    j = int(out.ids[0])
                    tp, fp = tp + int(gt[i, j]), fp + int(not gt[i, j])
            acc = tp + fp
            print(f"| {label} | {method} k={k:g} margin={margin:g} floor={floor:g} | {acc} | {tp / acc if acc else float('nan'):.3f} | "
                  f"{tp / max(int(has.sum()), 1):.3f} | {fp} |", flush=True)
    print(f"\n(recall over the {int(has.sum())} keyframes with a true match; min_samples 16)")


if __name__ == "__main__":
    main()
