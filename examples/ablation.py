"""The paper's Table 1: RMS-ATE of the SLAM system with each attention fusion, plus loop precision/recall.

Runs ``none`` (no attention), ``dam``, ``eam``, ``gaf`` and ``ega`` on one or more sequences and writes

* ``table1.md``: RMS-ATE (m) per sequence and the average, one row per fusion mode, then the loop-closure
  figures: accepted loops (true/false by ground truth) and the maximum recall at 100 % precision of the
  detector before and after geometric verification;
* ``pr_<sequence>.png``: precision/recall curves (before verification) of the five modes;
* ``<mode>/<sequence>/``: each run's trajectory.txt, loops.txt, metrics.json, trajectory.png.

Usage::

    python examples/ablation.py ../shared/data/7scenes-redkitchen --backbone efficientnet_lite0 --out runs/ablation \
        --rgb-intrinsics 525 525 320 240 --rgb-from-depth -0.025 0 0    # 7-Scenes: unregistered Kinect v1
    python examples/ablation.py ~/data/rgbd_dataset_freiburg1_room ~/data/rgbd_dataset_freiburg2_desk \
        --out runs/table1          # the paper's setting (VGG16 weights needed)
"""
import argparse
import json
import logging
from pathlib import Path

from slam.ablation import MODES, markdown_table, run_ablation


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sequences", nargs="+")
    p.add_argument("--out", default="runs/ablation")
    p.add_argument("--backbone", default="vgg16", choices=["vgg16", "efficientnet_lite0"])
    p.add_argument("--weights", default=None)
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--rgb-intrinsics", nargs=4, type=float, default=None, metavar=("FX", "FY", "CX", "CY"),
                   help="colour camera intrinsics of unregistered RGB-D (see attnloop-slam --help)")
    p.add_argument("--rgb-from-depth", nargs=3, type=float, default=None, metavar=("TX", "TY", "TZ"),
                   help="depth camera position in the colour camera, metres (with --rgb-intrinsics)")
    args = p.parse_args()
    logging.basicConfig(level=logging.WARNING)
    table = run_ablation(args.sequences, args.out, args.backbone, args.modes, args.max_frames, args.weights,
                         rgb_intrinsics=args.rgb_intrinsics, rgb_from_depth=args.rgb_from_depth)
    md = markdown_table(table)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / "table1.md").write_text(md)
    (Path(args.out) / "table1.json").write_text(json.dumps(table, indent=2, default=float))
    print(md)


if __name__ == "__main__":
    main()
