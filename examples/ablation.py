r"""The paper's Table 1: RMS-ATE of the SLAM system with each attention fusion, plus loop precision/recall.

Runs none (no attention), dam, eam, gaf and ega on one or more sequences and writes into --out:

  table1.md             RMS-ATE (m) per sequence and the average, one row per fusion mode, then the
                        loop-closure figures: accepted loops (true/false by ground truth) and the maximum
                        recall at 100 % precision of the detector before and after geometric verification
  table1.json           every run's metrics
  pr_<sequence>.png     precision/recall curves (before verification) of the modes
  <mode>/<sequence>/    each run's trajectory.txt, loops.txt, metrics.json, trajectory.png, map.ply

The options are attnloop-slam's (a 7-Scenes folder gets the Kinect v1 rig by default; --frame-step N
uses every Nth frame). Usage:

  python examples/ablation.py ../shared/data/7scenes-redkitchen --backbone efficientnet_lite0 --out runs/ablation
  python examples/ablation.py ../shared/data/7scenes-redkitchen --frame-step 6 --out runs/ablation_step6
  python examples/ablation.py ~/data/rgbd_dataset_freiburg1_room ~/data/rgbd_dataset_freiburg2_desk \
      --backbone vgg16 --out runs/table1          # the paper's setting (VGG16 weights needed)
"""
import argparse
import json
import logging
import sys
from pathlib import Path

from slam.ablation import MODES, markdown_table, run_ablation
from slam.cli import call_reporting_errors
from slam.options import add_run_arguments, given_options
from slam.pipeline import json_safe


def run(args: argparse.Namespace, given: frozenset[str] = frozenset()) -> int:
    table = run_ablation(args.sequences, args.out, args, modes=args.modes, given=given)
    md = markdown_table(table)
    (Path(args.out) / "table1.md").write_text(md)
    (Path(args.out) / "table1.json").write_text(json.dumps(json_safe(table), indent=2, allow_nan=False))
    print(md)
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="ablation.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sequences", nargs="+", help="TUM RGB-D or 7-Scenes sequence folders")
    p.add_argument("--out", default="runs/ablation", help="output folder (default: runs/ablation)")
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES),
                   help="fusion modes to run (default: all)")
    add_run_arguments(p, fusion=False)
    args = p.parse_args(argv)
    given = given_options(p, argv)  # the flags typed: those another makes idle are refused, as by attnloop-slam
    logging.basicConfig(level=logging.WARNING)
    # the command's messages for missing weights, a wrong folder, a bad flag (exit code 2)
    return call_reporting_errors("ablation.py", run, args, given)


if __name__ == "__main__":
    sys.exit(main())
