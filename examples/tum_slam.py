"""Run attention-guided loop-closing RGB-D SLAM on a TUM RGB-D (or 7-Scenes) sequence folder.

The same as the ``attnloop-slam`` console script, written out with the library calls so it can be
adapted::

    python examples/tum_slam.py ~/data/rgbd_dataset_freiburg1_room --out runs/fr1_room
    python examples/tum_slam.py ../shared/data/7scenes-redkitchen --out runs/kitchen \
        --backbone efficientnet_lite0

A TUM sequence (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/download, the .tgz unpacked) holds
rgb.txt, depth.txt and groundtruth.txt; the camera (fr1/fr2/fr3) is inferred from the folder name.
"""
import argparse
import logging

from slam.config import SLAMConfig
from slam.io import open_sequence
from slam.pipeline import evaluate_run, run_slam, write_outputs


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sequence")
    p.add_argument("--out", required=True)
    p.add_argument("--fusion", default="dam", choices=["none", "dam", "eam", "gaf", "ega"])
    p.add_argument("--backbone", default="vgg16", choices=["vgg16", "efficientnet_lite0"])
    p.add_argument("--weights", default=None, help="e.g. ~/.cache/torch/hub/checkpoints/vgg16-397923af.pth")
    p.add_argument("--camera", default=None, help="fr1 | fr2 | fr3 | ros (default: from the folder name)")
    p.add_argument("--max-frames", type=int, default=None)
    args = p.parse_args()
    logging.basicConfig(level=logging.WARNING)

    config = SLAMConfig()  # every threshold, with its default, lives in slam/config.py
    config.loop.descriptor.backbone = args.backbone
    config.loop.descriptor.fusion = args.fusion
    config.loop.descriptor.weights = args.weights

    sequence = open_sequence(args.sequence, camera=args.camera)
    run = run_slam(sequence, config, max_frames=args.max_frames)
    metrics = evaluate_run(run)
    write_outputs(run, args.out)
    print({k: metrics[k] for k in ("num_frames", "num_keyframes", "num_loops", "fps", "ate_rmse") if k in metrics})


if __name__ == "__main__":
    main()
