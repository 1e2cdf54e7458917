"""Trajectory (ATE / RPE, as evo) and loop-closure evaluation; place recognition is :mod:`attnloop.vpr.evaluate`.

Example:
    >>> import torch
    >>> from slam.io import Trajectory
    >>> t = torch.arange(10, dtype=torch.float64) / 30
    >>> poses = torch.zeros(10, 7, dtype=torch.float64); poses[:, 6] = 1; poses[:, 0] = t; poses[:, 1] = t * t
    >>> noisy = poses.clone(); noisy[::2, 2] += 0.01
    >>> result = ate(Trajectory(t, poses), Trajectory(t, noisy))
    >>> result.num_pairs, round(result.rmse, 4)
    (10, 0.0049)
"""
from slam.eval.align import transform_poses, umeyama_alignment
from slam.io.associate import TUM_MAX_DIFFERENCE, associate, associate_nearest, associate_trajectories
from slam.eval.loops import (
    LoopEvaluation,
    LoopGroundTruthConfig,
    PRCurve,
    evaluate_loop_candidates,
    ground_truth_loops,
    is_true_loop,
    plot_pr_curves,
    precision_recall_curve,
)
from slam.eval.metrics import ATEResult, ErrorStats, RPEResult, as_trajectory, ate, rpe
from slam.eval.plot import choose_plane, plot_trajectory

__all__ = [
    "TUM_MAX_DIFFERENCE",
    "ATEResult",
    "ErrorStats",
    "LoopEvaluation",
    "LoopGroundTruthConfig",
    "PRCurve",
    "RPEResult",
    "as_trajectory",
    "associate",
    "associate_nearest",
    "associate_trajectories",
    "ate",
    "choose_plane",
    "evaluate_loop_candidates",
    "ground_truth_loops",
    "is_true_loop",
    "plot_pr_curves",
    "plot_trajectory",
    "precision_recall_curve",
    "rpe",
    "transform_poses",
    "umeyama_alignment",
]
