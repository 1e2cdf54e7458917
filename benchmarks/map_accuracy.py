"""How well ``map.ply`` of a demo run lies on the synthetic room's surfaces (its geometry is known exactly).

Reads ``RUN/map.ply`` and ``RUN/demo_sequence/groundtruth.txt`` of an ``attnloop-slam --demo --out RUN``
run, moves the map into the room's frame with the ground-truth pose of the first frame (where the
estimate starts at the identity), and prints the number of points, the file size and the distance of the
points to the nearest surface of the room (median, 90 %, 99 %, share within 2 and 5 cm). The same is
printed after the rigid alignment of the whole trajectory to the ground truth (the ATE's), which
removes the start pose's own error.

    attnloop-slam --demo --out runs/demo
    python -m benchmarks.map_accuracy runs/demo
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from benchmarks._common import table
from slam.eval import ate
from slam.io import read_tum_trajectory
from slam.lie import quat_to_rotmat
from slam.mapping import read_ply
from slam.synthetic.scene import default_room_scene


def distances(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Distance (m) of ``R p + t`` to the nearest surface of the default room, per point."""
    room = torch.from_numpy((points @ R.T + t).astype(np.float32))
    scene = default_room_scene()
    return np.concatenate([scene.surface_distance(c).numpy() for c in torch.split(room, 200_000)])


def row(name: str, d: np.ndarray) -> list[str]:
    q = np.quantile(d, [0.5, 0.9, 0.99])
    return [name, *(f"{1000 * v:.1f}" for v in q), f"{100 * (d < 0.02).mean():.1f}", f"{100 * (d < 0.05).mean():.1f}"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path, help="the --out folder of an attnloop-slam --demo run")
    args = p.parse_args()
    pts, cols = read_ply(args.run / "map.ply")
    gt = read_tum_trajectory(args.run / "demo_sequence" / "groundtruth.txt")
    est = read_tum_trajectory(args.run / "trajectory.txt")
    g0 = gt.poses[0]
    a = ate(gt, est)
    print(f"{args.run}: {pts.shape[0]} points ({'coloured' if cols is not None else 'no colour'}), "
          f"{(args.run / 'map.ply').stat().st_size / 1e6:.2f} MB, trajectory ATE {a.rmse:.4f} m")
    print(table(["placed with", "median (mm)", "90 % (mm)", "99 % (mm)", "< 2 cm (%)", "< 5 cm (%)"],
                [row("first ground-truth pose", distances(pts, quat_to_rotmat(g0[3:]).numpy(), g0[:3].numpy())),
                 row("ATE alignment", distances(pts, a.rotation.numpy(), a.translation.numpy()))]))


if __name__ == "__main__":
    main()
