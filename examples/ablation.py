r"""The paper's Table 1: RMS-ATE of the SLAM system per sequence and descriptor, plus loop precision/recall.

With --preset paper (or guclu2019) the columns are the paper's: baseline (Guclu et al. 2019, the
guclu2019 preset: VGG16 pool5 without attention into 16 random RNNs, no channel merge) and GAF, EAM,
EGA, DAM (the paper preset with each fusion); VGG16's weights are required (--weights FILE, or
vgg16-397923af.pth in the torch hub cache). With --preset default (the default) the columns are our
fusion modes: none, dam, eam, gaf, ega. Writes into --out:

  table1.md             RMS-ATE (m), one row per sequence, an average row per camera group (fr1, fr2, fr3,
                        other), the paper's figure beside ours where slam.ablation.PAPER_TABLE1 has it; then
                        the loop closure: accepted loops (true/false by ground truth) and the maximum recall
                        at 100 % precision of the detector before and after geometric verification
  table1.json           every run's metrics
  pr_<sequence>.png     precision/recall curves (before verification) of the columns
  <column>/<sequence>/  each run's trajectory.txt, loops.txt, metrics.json, trajectory.png, map.ply and
                        config.toml (attnloop-slam --config of it repeats that run)

The options are attnloop-slam's (a 7-Scenes folder gets the Kinect v1 rig by default; --frame-step N
uses every Nth frame). Usage:

  python examples/ablation.py ../shared/data/7scenes-redkitchen --out runs/ablation
  python examples/ablation.py ../shared/data/7scenes-redkitchen --frame-step 6 --out runs/ablation_step6
  python examples/ablation.py ~/data/rgbd_dataset_freiburg1_room ~/data/rgbd_dataset_freiburg2_desk \
      --preset paper --weights vgg16-397923af.pth --out runs/table1     # the paper's descriptor and columns
"""
import argparse
import json
import logging
import sys
from pathlib import Path

from slam.ablation import markdown_table, run_ablation
from slam.cli import call_reporting_errors
from slam.options import add_run_arguments, given_settings, resolve_settings
from slam.outputs import json_safe
from slam.threads import limit_threads
from slam.viewer import VIEWER_FLAGS


def run(args: argparse.Namespace) -> int:
    # every folder and setting checked before the first run, as attnloop-slam checks them
    specs = [resolve_settings(given_settings(args), args.config_file, path) for path in args.sequences]
    with limit_threads(specs[0].config.threads):  # one thread limit for all the runs (docs/devices.md)
        table = run_ablation(specs, args.out, quiet=args.quiet)
    out = Path(args.out)
    md = markdown_table(table)
    (out / "table1.md").write_text(md)
    (out / "table1.json").write_text(json.dumps(json_safe(table), indent=2, allow_nan=False))
    print(md)
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="ablation.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sequences", nargs="+", help="TUM RGB-D or 7-Scenes sequence folders")
    p.add_argument("--out", default="runs/ablation", help="output folder (default: runs/ablation)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or per-run lines (the tables are printed)")
    add_run_arguments(p, exclude=("--fusion", *VIEWER_FLAGS))  # the columns set the fusion; a viewer shows one run
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    # the command's messages for missing weights, a wrong folder, a bad flag (exit code 2)
    return call_reporting_errors("ablation.py", run, args)


if __name__ == "__main__":
    sys.exit(main())
