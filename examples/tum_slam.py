"""Run attention-guided loop-closing RGB-D SLAM on a TUM RGB-D (or 7-Scenes) sequence folder.

The same as the attnloop-slam command, written out with the library calls so that it can be adapted:
open the sequence, build the config from the same options (slam.options), run, evaluate, write.

    python examples/tum_slam.py ~/data/rgbd_dataset_freiburg1_room --out runs/fr1_room
    python examples/tum_slam.py ../shared/data/7scenes-redkitchen --out runs/kitchen --backbone efficientnet_lite0

A TUM sequence (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/download, the .tgz unpacked) holds
rgb.txt, depth.txt and groundtruth.txt; the camera (fr1/fr2/fr3) is inferred from the folder name.
A 7-Scenes folder gets the Kinect v1 colour/depth rig by default; --rgb-intrinsics, --rgb-from-depth
and --registered override the rig of either.
"""
import argparse
import logging
import sys

import slam.allocator
from slam.cli import call_reporting_errors
from slam.io import open_sequence
from slam.options import add_run_arguments, config_from_args, given_options, reader_options
from slam.pipeline import evaluate_run, prepare_output_dir, run_slam, write_outputs


def run(args: argparse.Namespace, given: frozenset[str] = frozenset()) -> int:
    sequence = open_sequence(args.sequence, **reader_options(args))
    # every threshold, with its default, lives in slam/config.py; flags that others make idle are refused
    config = config_from_args(args, sequence, given=given)
    out = prepare_output_dir(args.out)  # checked (and the previous run's outputs removed) before the work
    run = run_slam(sequence, config, max_frames=args.max_frames, frame_step=args.frame_step)
    metrics = evaluate_run(run)
    write_outputs(run, out)
    keys = ("status", "failure", "num_frames", "num_keyframes", "num_loops", "fps", "backbone", "ate_rmse",
            "ate_unavailable")
    print({k: metrics[k] for k in keys if k in metrics})
    return 1 if metrics["status"] == "failed" else 0  # too few frames tracked: metrics.json alone, as attnloop-slam


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="tum_slam.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sequence", help="TUM RGB-D or 7-Scenes sequence folder")
    p.add_argument("--out", required=True, help="output folder")
    add_run_arguments(p)  # --fusion, --backbone, --weights, --frame-step, rig flags, ... as attnloop-slam
    args = p.parse_args(argv)
    given = given_options(p, argv)  # the flags typed (as attnloop-slam: --fusion with --no-loop is refused)
    logging.basicConfig(level=logging.WARNING)
    slam.allocator.keep_freed_memory()  # as attnloop-slam: this script owns its process (6-9 % more frames/s)
    # the command's messages for missing weights, a wrong folder, a bad flag (exit code 2)
    return call_reporting_errors("tum_slam.py", run, args, given)


if __name__ == "__main__":
    sys.exit(main())
