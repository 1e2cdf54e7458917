"""Run attention-guided loop-closing RGB-D SLAM on a TUM RGB-D (or 7-Scenes) sequence folder.

The same as the attnloop-slam command, written out with the library calls so that it can be adapted:
resolve the settings (the defaults, a --config file, the flags: slam.options), run, evaluate, write.

    python examples/tum_slam.py ~/data/rgbd_dataset_freiburg1_room --out runs/fr1_room
    python examples/tum_slam.py ~/data/rgbd_dataset_freiburg1_room --out runs/fr1_paper --preset paper
    python examples/tum_slam.py ../shared/data/7scenes-redkitchen --out runs/kitchen --backbone efficientnet_lite0

A TUM sequence (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/download, the .tgz unpacked) holds
rgb.txt, depth.txt and groundtruth.txt; the camera (fr1/fr2/fr3) is inferred from the folder name.
A 7-Scenes folder gets the Kinect v1 colour/depth rig by default; --rgb-intrinsics, --rgb-from-depth
and --registered override the rig of either. --preset paper runs the paper's descriptor (VGG16's
weights required: --weights FILE or vgg16-397923af.pth in the torch hub cache).
"""
import argparse
import logging
import sys

from slam.cli import call_reporting_errors
from slam.options import add_run_arguments, given_settings, resolve_settings
from slam.outputs import prepare_output_dir, write_outputs
from slam.pipeline import run_slam
from slam.report import evaluate_run
from slam.threads import limit_threads
from slam.viewer import check_viewer, open_viewer


def run(args: argparse.Namespace) -> int:
    # every threshold, with its default, lives in slam/config.py; flags that others make idle are refused
    spec = resolve_settings(given_settings(args), args.config_file, args.sequence)
    check_viewer(spec.run)  # --viewer, --connect, --rrd: rerun installed, the file writable
    out = prepare_output_dir(args.out)  # checked (and the previous run's outputs removed) before the work
    spec.save(out / "config.toml")  # --config of it repeats the run
    opts = spec.run
    viewer = open_viewer(opts, name=spec.sequence.name)  # None without those flags
    with limit_threads(spec.config.threads):  # one thread limit for the whole work (docs/devices.md)
        try:
            run = run_slam(spec.sequence, spec.config, max_frames=opts.max_frames, frame_step=opts.frame_step,
                           frames=opts.frames, observer=viewer)
        finally:
            if viewer is not None:
                viewer.close()
        metrics = evaluate_run(run).as_dict()
        write_outputs(run, out)
    keys = ("status", "failure", "num_frames", "num_keyframes", "num_loops", "fps", "descriptor", "ate_rmse",
            "ate_unavailable")
    print({k: metrics[k] for k in keys if k in metrics})
    return 1 if metrics["status"] == "failed" else 0  # too few frames tracked: metrics.json alone, as attnloop-slam


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="tum_slam.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sequence", help="TUM RGB-D or 7-Scenes sequence folder")
    p.add_argument("--out", required=True, help="output folder")
    add_run_arguments(p)  # --config, --preset, --fusion, --backbone, --weights, --frame-step, rig flags, ...
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    # the command's messages for missing weights, a wrong folder, a bad flag (exit code 2)
    return call_reporting_errors("tum_slam.py", run, args)


if __name__ == "__main__":
    sys.exit(main())
