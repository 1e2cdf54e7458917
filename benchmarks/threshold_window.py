"""Adaptive loop-candidate threshold on real descriptors (7-Scenes redkitchen): precision and recall by window and k_sigma.

Every frame is a keyframe (id = frame index); the default detector (``LoopDetectorConfig``: top_k 5, MAD
threshold) runs over all 1000 frames with the given exclusion window and ``k_sigma``, and its accepted
candidates are scored by ground truth (a match: frames < 0.5 m and < 45 degrees apart). The descriptors
(EfficientNet-Lite0 per fusion mode) are computed once and cached in ``out/``.

Usage:
    python benchmarks/threshold_window.py                       # fusion none and dam, windows 30 and 150
    python benchmarks/threshold_window.py --fusion dam --windows 30 --k-sigma 3

Prints markdown tables (docs/benchmarks.md, "Adaptive threshold on real descriptors").
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from index_data import real_descriptors

from attnloop.index import LoopCandidateDetector, LoopDetectorConfig
from attnloop.threshold import ThresholdConfig


def gt_matches(T: np.ndarray, max_dist: float, max_angle_deg: float) -> np.ndarray:
    """(N, N) bool: frames closer than max_dist metres and max_angle_deg degrees (camera-to-world T)."""
    t, R = T[:, :3, 3], T[:, :3, :3]
    dist = np.linalg.norm(t[:, None] - t[None], axis=-1)
    cos = np.clip((np.einsum("iab,jab->ij", R, R) - 1.0) / 2.0, -1.0, 1.0)
    return (dist < max_dist) & (np.degrees(np.arccos(cos)) < max_angle_deg)


def detector_eval(desc: torch.Tensor, gt: np.ndarray, window: int, k_sigma: float) -> str:
    """Run LoopCandidateDetector over all frames (id = frame index) and score its output by ground truth."""
    cfg = LoopDetectorConfig(window=window, threshold=ThresholdConfig(k_sigma=k_sigma))
    det = LoopCandidateDetector(cfg)
    n = desc.shape[0]
    top_true = top_false = cand_true = cand_false = with_match = 0
    for i in range(n):
        out = det.add_and_query(desc[i], keyframe_id=i)
        if i - window >= 0 and gt[i, : i - window + 1].any():
            with_match += 1
        ids = out.ids.tolist()
        if ids:
            top_true += bool(gt[i, ids[0]])
            top_false += not gt[i, ids[0]]
            good = sum(bool(gt[i, j]) for j in ids)
            cand_true += good
            cand_false += len(ids) - good
    prec = top_true / max(top_true + top_false, 1)
    cprec = cand_true / max(cand_true + cand_false, 1)
    return (f"| {window} | {k_sigma:g} | {with_match} | {top_true + top_false} | {prec:.3f} | "
            f"{top_true / max(with_match, 1):.3f} | {cand_true + cand_false} | {cprec:.3f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fusion", nargs="+", default=["none", "dam"], help="fusion modes")
    ap.add_argument("--backbone", default="efficientnet_lite0", help="descriptor backbone")
    ap.add_argument("--windows", type=int, nargs="+", default=[30, 150], help="exclusion windows (frames)")
    ap.add_argument("--k-sigma", type=float, nargs="+", default=[2.0, 3.0, 4.0, 5.0], help="threshold multipliers k to compare")
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"# loop-candidate threshold on redkitchen ({args.backbone}, {time.strftime('%Y-%m-%d')})\n")
    print("Every frame a keyframe (id = frame index); a match is true when the frames are < 0.5 m and "
          "< 45 deg apart by ground truth. Default detector (top_k 5, MAD threshold) with the given window "
          "and k_sigma.")
    for mode in args.fusion:
        data = real_descriptors(args.backbone, mode)
        gt = gt_matches(data["kitchen_poses"].numpy(), 0.5, 45.0)
        print(f"\n{mode}:\n")
        print("| window | k_sigma | queries with a true match | top-1 accepted | top-1 precision "
              "| top-1 recall | candidates accepted | candidate precision |")
        print("|---:|---:|---:|---:|---:|---:|---:|---:|")
        for w in args.windows:
            for k in args.k_sigma:
                print(detector_eval(data["kitchen"].float(), gt, w, k), flush=True)


if __name__ == "__main__":
    main()
