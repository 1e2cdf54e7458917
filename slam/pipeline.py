"""Run the SLAM system over a sequence, evaluate it and write the standard outputs.

The command line (:mod:`slam.cli`) and the examples only parse arguments and call these functions.

Outputs written by :func:`write_outputs` into a folder:

* ``trajectory.txt``: TUM format, one pose per input frame, in input order;
* ``loops.txt``: one accepted loop per line, ``timestamp_a timestamp_b`` (the two keyframes' own stamps);
* ``metrics.json``: ``ate_rmse`` (when ground truth exists), ``num_loops``, ``fps`` and more;
* ``trajectory.png``: the estimate (and ground truth) seen from above with the loop edges.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Optional, Union

import numpy as np
import torch

from slam.config import SLAMConfig
from slam.io.images import FrameReadError
from slam.io.sequence import RGBDSequence
from slam.io.trajectory import Trajectory, write_tum_trajectory
from slam.progress import Progress
from slam.system import RGBDSLAM, SLAMResult

logger = logging.getLogger(__name__)

__all__ = ["RunResult", "run_slam", "evaluate_run", "write_outputs"]


@dataclass
class RunResult:
    """A finished run: the system's result plus wall-clock figures.

    Attributes:
        result: :class:`slam.system.SLAMResult`.
        sequence_name: name of the sequence.
        wall_seconds: time of the whole run (reading, tracking, loops, final optimisation).
        fps: input frames per second over ``wall_seconds``.
        groundtruth: per-frame ground truth (input order) or None.
        gt_poses_per_frame: ``(N, 7)`` ground truth of each processed frame (NaN where unknown).
        metrics: filled by :func:`evaluate_run`.
        loop_curves: ``{"before_verification": PRCurve, "after_verification": PRCurve}`` (with ground truth).
    """

    result: SLAMResult
    sequence_name: str
    wall_seconds: float
    fps: float
    groundtruth: Optional[Trajectory]
    gt_poses_per_frame: Optional[torch.Tensor]
    metrics: Dict[str, object] = field(default_factory=dict)
    loop_curves: Dict[str, object] = field(default_factory=dict)


def run_slam(sequence: RGBDSequence, config: Optional[SLAMConfig] = None, max_frames: Optional[int] = None,
             progress: Optional[bool] = None, descriptor: Optional[torch.nn.Module] = None,
             prefetch: int = 2) -> RunResult:
    """Track every frame of ``sequence`` and optimise.

    A frame that cannot be read (missing or corrupt image) is skipped with a warning and placed by constant
    velocity, so the trajectory still has one pose per input frame.

    Args:
        sequence: an opened sequence (:func:`slam.io.open_sequence`).
        config: :class:`slam.config.SLAMConfig`.
        max_frames: process only the first ``max_frames`` frames.
        progress: show a progress bar (None: when stderr is a terminal).
        descriptor: a prebuilt descriptor model (else built from the config).
        prefetch: frames decoded ahead in background threads.

    Returns:
        :class:`RunResult`.
    """
    n = len(sequence) if max_frames is None else min(int(max_frames), len(sequence))
    if n <= 0:
        raise ValueError(f"{sequence.name}: nothing to process (max_frames={max_frames}, {len(sequence)} frames)")
    view = sequence[:n]
    stamps = view.timestamps
    slam = RGBDSLAM(config, descriptor=descriptor)
    start = time.perf_counter()
    # decode ahead in threads; an unreadable frame comes as its FrameReadError, so it is only skipped
    bar = Progress(range(n), total=n, desc=sequence.name, enabled=progress)
    frames = view.frames(on_error="yield", prefetch=prefetch)
    for i in bar:
        with slam.timer("io_wait"):  # decoding runs ahead in threads: this is only the time waited for it
            frame_or_error = next(frames)
        if isinstance(frame_or_error, FrameReadError):
            slam.skip(i, float(stamps[i]), str(frame_or_error))
        else:
            slam.track(frame_or_error)
        if i % 10 == 0:
            bar.set_postfix(f"kf={len(slam.keyframes)} loops={len(slam.loops)}")
    result = slam.finish()
    wall = time.perf_counter() - start
    gt = view.groundtruth
    gt_arr = torch.from_numpy(np.stack([
        p if p is not None else np.full(7, np.nan) for p in (view.groundtruth_pose(i) for i in range(n))
    ])) if gt is not None else None
    return RunResult(result, sequence.name, wall, n / max(wall, 1e-9), gt, gt_arr)


def evaluate_run(run: RunResult, loop_gt=None) -> Dict[str, object]:
    """Compute the metrics of a run (stored in ``run.metrics`` and returned).

    Keys: ``sequence``, ``num_frames``, ``num_keyframes``, ``num_loops``, ``num_lost``, ``num_skipped``,
    ``fps``, ``wall_seconds``, ``time_per_stage``; with ground truth also ``ate_rmse`` (rigid SE(3)
    alignment, TUM association), ``ate`` (statistics), ``odometry_ate_rmse`` (before the pose graph),
    ``rpe_1frame`` / ``rpe_1s`` (translation m, rotation deg) and ``loops_true`` / ``loops_false``
    (accepted loops judged by ground-truth distance and angle, :class:`slam.eval.LoopGroundTruthConfig`).

    Args:
        run: a :class:`RunResult`.
        loop_gt: :class:`slam.eval.LoopGroundTruthConfig` for judging loops (default thresholds).
    """
    from slam.eval import LoopGroundTruthConfig, ate, is_true_loop, rpe

    res = run.result
    m: Dict[str, object] = {
        "sequence": run.sequence_name,
        "num_frames": res.num_frames,
        "num_keyframes": res.num_keyframes,
        "num_loops": len(res.loops),
        "num_lost": res.num_lost,
        "num_skipped": res.num_skipped,
        "fps": round(run.fps, 3),
        "wall_seconds": round(run.wall_seconds, 3),
        "time_per_stage": res.timings,
    }
    if res.optimization is not None:
        opt = res.optimization
        m["pose_graph"] = {"keyframes": res.graph.num_poses, "edges": res.graph.num_edges,
                           "initial_chi2": opt.initial_chi2, "chi2": opt.chi2, "status": str(opt.status),
                           "iterations": opt.iterations}
    if run.groundtruth is not None and len(run.groundtruth) >= 3:
        a = ate(run.groundtruth, res.trajectory)
        m["ate_rmse"] = a.rmse
        m["ate"] = {"rmse": a.rmse, "mean": a.mean, "median": a.median, "std": a.std, "max": a.max,
                    "num_pairs": a.num_pairs}
        m["odometry_ate_rmse"] = ate(run.groundtruth, res.odometry_trajectory).rmse
        for key, kw in (("rpe_1frame", dict(delta=1, delta_unit="frames")),
                        ("rpe_1s", dict(delta=1.0, delta_unit="seconds"))):
            try:
                r = rpe(run.groundtruth, res.trajectory, **kw)
                m[key] = {"trans_rmse_m": r.translation.rmse, "rot_rmse_deg": r.rotation.rmse,
                          "num_pairs": int(r.pairs.shape[0])}
            except ValueError as e:  # too short for the delta
                m[key] = {"error": str(e)}
        cfg = loop_gt or LoopGroundTruthConfig()
        gt = run.gt_poses_per_frame
        # an accepted loop is judged by closeness alone (the frame-gap rule is for counting revisits)
        pairs = torch.tensor([[lp.frame_b, lp.frame_a] for lp in res.loops], dtype=torch.long).reshape(-1, 2)
        judged = is_true_loop(gt, pairs, dataclasses.replace(cfg, min_frame_gap=1))
        m["loops_true"] = int(judged.sum())
        m["loops_false"] = int((~judged).sum())
        m["loop_detection"] = loop_precision_recall(run, cfg)
    run.metrics = m
    return m


def loop_precision_recall(run: RunResult, config=None) -> Dict[str, object]:
    """Precision/recall of the loop detector over the keyframe queries, before and after verification.

    Each query keyframe contributes its best candidate: before verification the most similar eligible
    keyframe scored by similarity; after verification the most similar *verified* candidate (queries with
    none score ``-inf``). Positives are the ground-truth revisits among the keyframes
    (:func:`slam.eval.ground_truth_loops`).

    Returns:
        ``{"before_verification": {...}, "after_verification": {...}}`` with ``max_recall_at_full_precision``,
        ``average_precision`` and ``num_positives``; the curves themselves go to ``run.loop_curves``.
    """
    from slam.eval import LoopGroundTruthConfig, evaluate_loop_candidates

    cfg = config or LoopGroundTruthConfig()
    res = run.result
    frames = res.keyframe_frames
    if run.gt_poses_per_frame is None or not res.queries:
        return {}
    verified_sim = {}
    for lp in res.loops:
        verified_sim[lp.kf_b] = max(verified_sim.get(lp.kf_b, float("-inf")), lp.similarity)
    before_pairs, before_scores, after_pairs, after_scores = [], [], [], []
    for q in res.queries:
        if q.top_kf < 0:
            continue
        before_pairs.append([int(frames[q.kf]), int(frames[q.top_kf])])
        before_scores.append(q.top_score)
        best = q.verified[0] if q.verified else q.top_kf
        after_pairs.append([int(frames[q.kf]), int(frames[best])])
        after_scores.append(verified_sim.get(q.kf, float("-inf")) if q.verified else float("-inf"))
    if not before_pairs:
        return {}
    out: Dict[str, object] = {}
    for name, pairs, scores in (("before_verification", before_pairs, before_scores),
                                ("after_verification", after_pairs, after_scores)):
        ev = evaluate_loop_candidates(torch.tensor(pairs), torch.tensor(scores, dtype=torch.float64),
                                      run.gt_poses_per_frame, cfg, mode="best_per_query", indices=frames)
        out[name] = ev.curve.to_dict()
        run.loop_curves[name] = ev.curve
    return out


def write_outputs(run: RunResult, out_dir: Union[str, os.PathLike], plot: bool = True) -> Path:
    """Write ``trajectory.txt``, ``loops.txt``, ``metrics.json`` and ``trajectory.png`` into ``out_dir``.

    Args:
        run: an evaluated :class:`RunResult` (:func:`evaluate_run` is called if it was not).
        out_dir: created if needed.
        plot: also draw ``trajectory.png``.

    Returns:
        the output folder.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if not run.metrics:
        evaluate_run(run)
    res = run.result
    write_tum_trajectory(out / "trajectory.txt", res.trajectory)
    with open(out / "loops.txt", "w") as f:
        f.write("# timestamp_a timestamp_b  (accepted loop closures between keyframes)\n")
        for lp in res.loops:
            f.write(f"{lp.timestamp_a:.6f} {lp.timestamp_b:.6f}\n")
    with open(out / "metrics.json", "w") as f:
        json.dump(run.metrics, f, indent=2, default=float)
    if plot:
        from slam.eval import plot_trajectory

        loops = torch.tensor([[lp.timestamp_a, lp.timestamp_b] for lp in res.loops], dtype=torch.float64
                             ).reshape(-1, 2)
        ate_txt = f", ATE {run.metrics['ate_rmse'] * 100:.1f} cm" if "ate_rmse" in run.metrics else ""
        plot_trajectory(out / "trajectory.png", res.trajectory, run.groundtruth, loops=loops,
                        title=f"{run.sequence_name}: {len(res.loops)} loops{ate_txt}")
    return out
