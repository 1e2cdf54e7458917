"""A covered lens on a real sequence: tracking is lost, and loops across the gap must mend the guess.

    python benchmarks/tracking_loss.py [--data ../shared/data] [--gaps 300:400 500:600 700:800] [--threads N]
    python benchmarks/tracking_loss.py --sequence runs/building_seq --gaps 650:780   # another sequence folder

7-Scenes redkitchen (1000 real frames; or ``--sequence``) run through :class:`slam.system.RGBDSLAM` with
the configuration ``attnloop-slam`` gives it (the Kinect rig of 7-Scenes, the default loop descriptor),
once as recorded and once per gap ``A:B`` with the depth of frames A..B-1 blanked (a covered lens: no
depth, so no registration). The front end reports those frames lost and then forces a keyframe
at its constant-velocity guess with a *weak* edge: a guess, not a measurement. Each row: the frames lost,
the weak edges, the loops kept and how many join keyframes on both sides of the gap, how many loops
disagree with the ground truth's relative pose by more than 0.1 m, and the ATE (m) of the tracked frames
(every frame not lost), for the optimised trajectory and for odometry alone (the reference, from the same
run), then over every frame (the lost ones interpolated between the tracked ones around them). The loops
across a gap are what corrects the guess: no measured path joins their keyframes
(:meth:`slam.keyframe_graph.KeyframeGraph.path_lengths`), so they are held to the drift bound's caps only,
or with ``--recover-after-loss`` (``LoopClosureConfig.recover_after_loss``) to no bound, the group check alone.
"""
from __future__ import annotations

import argparse
import logging
import os
import time
from pathlib import Path

import numpy as np
import torch

from slam.config import SLAMConfig, override
from slam.eval.metrics import ate
from slam.io import open_sequence
from slam.io.sevenscenes import SevenScenesSequence
from slam.io.trajectory import Trajectory
from slam.lie import se3_between
from slam.loop.closer import build_descriptor
from slam.options import resolve_settings
from slam.system import RGBDSLAM


def parse_gap(text: str) -> tuple[int, int]:
    a, _, b = text.partition(":")
    try:
        start, end = int(a), int(b)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a gap is FIRST:END (frames FIRST .. END-1), got {text!r}") from None
    if not 0 <= start < end:
        raise argparse.ArgumentTypeError(f"a gap needs 0 <= FIRST < END, got {text!r}")
    return start, end


def config(seq, recover_after_loss: bool = False, threads: int | None = None) -> SLAMConfig:
    """What ``attnloop-slam`` runs on ``seq`` (its dataset's rig), with the default descriptor's backbone named
    and no point cloud (not measured here); ``recover_after_loss``: ``LoopClosureConfig.recover_after_loss``;
    ``threads``: ``SLAMConfig.threads`` (None: its default)."""
    cfg = resolve_settings({"loop.descriptor.backbone": "efficientnet_lite0", "map.enabled": False, "threads": threads},
                           sequence=seq).config
    cfg = override(cfg, {"loop.recover_after_loss": recover_after_loss})
    return cfg


def run(seq, descriptor, gap: tuple[int, int] | None, recover_after_loss: bool = False,
        threads: int | None = None) -> dict:
    """One run of ``seq`` (any sequence with ground truth, or a slice of one); ``gap``: the frames whose depth
    is blanked (None: as recorded). Frames without ground truth are left out of the ATE and the loop check."""
    slam = RGBDSLAM(config(seq, recover_after_loss, threads), descriptor=descriptor)
    a, b = gap or (0, 0)
    tracked, t0 = [], time.perf_counter()
    for i in range(len(seq)):
        frame = seq[i]
        if a <= i < b:
            frame.depth = np.zeros_like(frame.depth)
        tracked.append(slam.track(frame).status != "lost")
    res = slam.finish()
    gt = torch.from_numpy(np.stack([p if p is not None else np.full(7, np.nan)
                                    for p in (seq.groundtruth_pose(i) for i in range(len(seq)))]))
    known = torch.isfinite(gt).all(dim=1)
    stamps = torch.from_numpy(seq.timestamps)
    tracked = torch.tensor(tracked)

    def rmse(traj: Trajectory, keep: torch.Tensor) -> float:
        keep = keep & known
        return ate(Trajectory(stamps[keep], gt[keep]), Trajectory(traj.timestamps[keep], traj.poses[keep])).rmse

    everything = torch.ones_like(tracked)
    wrong = sum(float(se3_between(lp.T_ab, se3_between(gt[lp.frame_a], gt[lp.frame_b]))[:3].norm()) > 0.1
                for lp in res.loops if known[lp.frame_a] and known[lp.frame_b])
    return {"gap": "none" if gap is None else f"{a}-{b - 1}", "lost": int((~tracked).sum()),
            "weak": sum(e.weak for e in slam.graph.edges), "loops": len(res.loops),
            "across": sum(lp.frame_a < a and lp.frame_b >= b for lp in res.loops) if gap else 0, "wrong": wrong,
            "ate": rmse(res.trajectory, tracked), "ate_odo": rmse(res.odometry_trajectory, tracked),
            "ate_all": rmse(res.trajectory, everything), "ate_all_odo": rmse(res.odometry_trajectory, everything),
            "seconds": time.perf_counter() - t0}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", type=Path, default=Path(os.environ.get("ATTNLOOP_DATA", "../shared/data")),
                   help="the shared data folder (default: ATTNLOOP_DATA or ../shared/data)")
    p.add_argument("--gaps", nargs="+", type=parse_gap, default=[(300, 400), (500, 600), (700, 800)],
                   metavar="FIRST:END", help="frames whose depth is blanked, one run each (default: 300:400 "
                                             "500:600 700:800)")
    p.add_argument("--sequence", type=Path, default=None, metavar="DIR",
                   help="a sequence folder with ground truth (TUM, 7-Scenes, generated) instead of the kitchen")
    p.add_argument("--recover-after-loss", action="store_true",
                   help="LoopClosureConfig.recover_after_loss: no bound on loops across a loss")
    p.add_argument("--threads", type=int, default=None,
                   help="threads of the SLAM runs (SLAMConfig.threads; default: its own, 1)")
    args = p.parse_args()
    logging.getLogger("slam").setLevel(logging.ERROR)  # not a line per covered frame (they are counted)
    if args.sequence is not None:
        seq = open_sequence(args.sequence)
        if seq.groundtruth is None:
            raise SystemExit(f"{args.sequence}: no ground truth to measure against")
    else:
        folder = args.data / "7scenes-redkitchen"
        if not (folder / "frame-000000.color.jpg").is_file():
            raise SystemExit(f"{folder}: 7-Scenes redkitchen not found (set ATTNLOOP_DATA or --data)")
        seq = SevenScenesSequence(folder)
    for a, b in args.gaps:
        if b > len(seq):
            p.error(f"gap {a}:{b} ends past the sequence's {len(seq)} frames")
    cfg = config(seq, args.recover_after_loss, args.threads)  # what every run below builds
    desc = build_descriptor(cfg.loop.descriptor)
    mode = ", recover_after_loss" if args.recover_after_loss else ""
    print(f"# A covered lens on {seq.name} ({time.strftime('%Y-%m-%d %H:%M')}, torch {torch.__version__}, "
          f"{cfg.threads} thread(s){mode})\n")
    print("| depth blanked | frames lost | weak edges | loops (across the gap) | loops > 0.1 m off | ATE tracked "
          "frames: optimised / odometry (m) | ATE all frames: optimised / odometry (m) | s |")
    print("|---|---|---|---|---|---|---|---|")
    for gap in [None, *args.gaps]:
        r = run(seq, desc, gap, args.recover_after_loss, args.threads)
        print(f"| {r['gap']} | {r['lost']} | {r['weak']} | {r['loops']} ({r['across']}) | {r['wrong']} | "
              f"{r['ate']:.4f} / {r['ate_odo']:.4f} | {r['ate_all']:.4f} / {r['ate_all_odo']:.4f} | "
              f"{r['seconds']:.0f} |", flush=True)


if __name__ == "__main__":
    main()
