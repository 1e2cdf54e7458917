"""Loop-closure evaluation: ground-truth loop pairs, precision/recall, and the PR-curve figure.

Frames ``(i, j)`` are a **true loop** when, by ground truth, the camera centres are less than ``max_distance``
apart, the orientations less than ``max_angle_deg``, and the indices at least ``min_frame_gap`` (NaN poses: never).
A detector is scored per query (its best candidate, a detection when its score >= the threshold; non-finite scores
never are); recall counts the queries that have a true partner *earlier* among ``indices``.

Example:
    >>> scores = torch.tensor([0.9, 0.8, 0.7, 0.6])
    >>> labels = torch.tensor([True, True, False, True])
    >>> curve = precision_recall_curve(scores, labels)
    >>> round(curve.max_recall_at_full_precision, 3), curve.precision.shape
    (0.667, torch.Size([5]))
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from slam.eval.plot import plot_pr_curves

__all__ = [
    "LoopEvaluation",
    "LoopGroundTruthConfig",
    "PRCurve",
    "evaluate_loop_candidates",
    "ground_truth_loops",
    "is_true_loop",
    "plot_pr_curves",
    "precision_recall_curve",
]


@dataclass(frozen=True)
class LoopGroundTruthConfig:
    """When two frames count as a true loop (by ground truth)."""

    max_distance: float = 0.5  # metres between the camera centres (strictly less)
    max_angle_deg: float = 45.0  # degrees between the orientations (strictly less)
    min_frame_gap: int = 100  # frames (3.3 s at 30 Hz): nearer frames are odometry, not a revisit

    def __post_init__(self):
        if not (self.max_distance > 0 and 0 < self.max_angle_deg <= 180 and self.min_frame_gap >= 1):
            raise ValueError(f"invalid loop ground-truth config {self}")


def _check_poses(poses: torch.Tensor) -> torch.Tensor:
    if not isinstance(poses, torch.Tensor):
        poses = torch.as_tensor(np.asarray(poses), dtype=torch.float64)
    if poses.dim() != 2 or poses.shape[-1] != 7:
        raise ValueError(f"poses must have shape (N, 7), got {tuple(poses.shape)}")
    return poses.to(torch.float64)


def poses_close(pa: torch.Tensor, pb: torch.Tensor, cfg: LoopGroundTruthConfig) -> torch.Tensor:
    """Pairwise-broadcast closeness of poses ``(..., 7)``: distance and angle below the thresholds."""
    dist = (pa[..., :3] - pb[..., :3]).norm(dim=-1)
    qa = pa[..., 3:] / pa[..., 3:].norm(dim=-1, keepdim=True)
    qb = pb[..., 3:] / pb[..., 3:].norm(dim=-1, keepdim=True)
    # angle(qa^-1 qb) < a  <=>  |<qa, qb>| > cos(a / 2) for unit quaternions
    cos_half = (qa * qb).sum(dim=-1).abs()
    return (dist < cfg.max_distance) & (cos_half > math.cos(math.radians(cfg.max_angle_deg) / 2))


def is_true_loop(poses: torch.Tensor, pairs: torch.Tensor, config: LoopGroundTruthConfig = LoopGroundTruthConfig()
                 ) -> torch.Tensor:
    """Whether each frame pair is a true loop.

    Args:
        poses: ``(N, 7)`` ground truth per frame (NaN rows: unknown).
        pairs: ``(M, 2)`` int64 frame indices (any order within a pair).
        config: thresholds.

    Returns:
        ``(M,)`` bool.
    """
    poses = _check_poses(poses)
    pairs = torch.as_tensor(pairs, dtype=torch.long).reshape(-1, 2).to(poses.device)
    if pairs.numel() and (pairs.min() < 0 or pairs.max() >= poses.shape[0]):
        raise ValueError(f"pair indices must be in [0, {poses.shape[0]}), got {pairs.min()}..{pairs.max()}")
    gap = (pairs[:, 0] - pairs[:, 1]).abs() >= config.min_frame_gap
    return gap & poses_close(poses[pairs[:, 0]], poses[pairs[:, 1]], config)


def ground_truth_loops(poses: torch.Tensor, config: LoopGroundTruthConfig = LoopGroundTruthConfig(),
                       indices: torch.Tensor | None = None, chunk: int = 2048) -> torch.Tensor:
    """All true loop pairs ``(i, j)`` with ``i > j`` (a later query and an earlier match).

    Args:
        poses: ``(N, 7)`` ground truth per frame (NaN rows: unknown).
        config: thresholds.
        indices: ``(K,)`` frame indices taking part (e.g. the keyframes); default all frames.
        chunk: rows processed at once (memory ``chunk x K``).

    Returns:
        ``(L, 2)`` int64 frame indices, sorted by ``i`` then ``j``.
    """
    poses = _check_poses(poses)
    idx = torch.arange(poses.shape[0]) if indices is None else torch.as_tensor(indices, dtype=torch.long).flatten()
    idx = torch.unique(idx).to(poses.device)  # sorted
    sel = poses[idx]
    pos = sel[:, :3]
    q = sel[:, 3:] / sel[:, 3:].norm(dim=-1, keepdim=True)
    cos_max = math.cos(math.radians(config.max_angle_deg) / 2)
    out = []
    for s in range(0, idx.numel(), chunk):
        rows = idx[s:s + chunk]
        # the same tests as poses_close, as matrices: exact distances (no |a|^2 - 2ab + |b|^2 shortcut)
        dist = torch.cdist(pos[s:s + chunk], pos, compute_mode="donot_use_mm_for_euclid_dist")
        ok = (dist < config.max_distance) & ((q[s:s + chunk] @ q.T).abs() > cos_max)
        ok &= (rows[:, None] - idx[None, :]) >= config.min_frame_gap
        r, c = torch.nonzero(ok, as_tuple=True)
        out.append(torch.stack([rows[r], idx[c]], dim=-1))
    return torch.cat(out) if out else torch.zeros(0, 2, dtype=torch.long)


@dataclass
class PRCurve:
    """A precision/recall curve, one point per distinct score threshold (high to low).

    Attributes:
        precision: ``(K + 1,)`` float64; the first point is ``(recall 0, precision 1)``.
        recall: ``(K + 1,)`` float64.
        thresholds: ``(K + 1,)`` float64: a prediction counts when its score >= threshold (first: +inf).
        num_positives: the recall denominator.
        max_recall_at_full_precision: the largest recall reached with no false positive.
        threshold_at_full_precision: the threshold reaching it (+inf when it is 0).
        average_precision: ``sum_k (R_k - R_{k-1}) P_k``.
    """

    precision: torch.Tensor = field(repr=False)
    recall: torch.Tensor = field(repr=False)
    thresholds: torch.Tensor = field(repr=False)
    num_positives: int
    max_recall_at_full_precision: float
    threshold_at_full_precision: float
    average_precision: float

    def to_dict(self) -> dict[str, float]:
        """The scalars, keyed by their attribute names (strict JSON: an infinite threshold becomes None)."""
        thr = self.threshold_at_full_precision
        return {"num_positives": self.num_positives,
                "max_recall_at_full_precision": self.max_recall_at_full_precision,
                "threshold_at_full_precision": thr if math.isfinite(thr) else None,
                "average_precision": self.average_precision}


def precision_recall_curve(scores: torch.Tensor, labels: torch.Tensor, num_positives: int | None = None
                           ) -> PRCurve:
    """Precision/recall of thresholding ``scores`` (higher = more likely a loop).

    Args:
        scores: ``(M,)`` scores; non-finite entries are never predicted positive.
        labels: ``(M,)`` bool: the prediction is correct.
        num_positives: the recall denominator (default: ``labels.sum()``). It may exceed the number of
            true predictions (loops no candidate found).

    Returns:
        a :class:`PRCurve`.
    """
    scores = torch.as_tensor(scores).detach().to("cpu", torch.float64).flatten()
    labels = torch.as_tensor(labels).detach().to("cpu").bool().flatten()
    if scores.shape != labels.shape:
        raise ValueError(f"scores and labels must have the same shape (M,), got {tuple(scores.shape)} and "
                         f"{tuple(labels.shape)}")
    finite = torch.isfinite(scores)
    if num_positives is None:
        num_positives = int(labels.sum())
    true_predictions = int((labels & finite).sum())
    if num_positives < true_predictions:
        raise ValueError(f"num_positives={num_positives} is less than the {true_predictions} true predictions")
    scores, labels = scores[finite], labels[finite]
    order = torch.argsort(scores, descending=True, stable=True)
    s, y = scores[order], labels[order].to(torch.float64)
    tp, fp = torch.cumsum(y, 0), torch.cumsum(1.0 - y, 0)
    last = torch.ones_like(s, dtype=torch.bool)  # last element of each group of equal scores
    last[:-1] = s[1:] != s[:-1]
    tp, fp, thr = tp[last], fp[last], s[last]
    one = torch.ones(1, dtype=torch.float64)
    precision = torch.cat([one, tp / (tp + fp)])
    recall = torch.cat([0 * one, tp / num_positives if num_positives > 0 else 0 * tp])
    thresholds = torch.cat([one * math.inf, thr])
    fp_all = torch.cat([0 * one, fp])
    perfect = torch.nonzero(fp_all == 0).flatten()
    k = int(perfect[-1])
    ap = float(((recall[1:] - recall[:-1]) * precision[1:]).sum())
    return PRCurve(precision, recall, thresholds, int(num_positives), float(recall[k]), float(thresholds[k]), ap)


@dataclass
class LoopEvaluation:
    """The result of :func:`evaluate_loop_candidates`.

    Attributes:
        curve: the precision/recall curve.
        pairs: ``(P, 2)`` the evaluated predictions (query, candidate).
        scores: ``(P,)`` their scores.
        labels: ``(P,)`` bool: true loop.
    """

    curve: PRCurve
    pairs: torch.Tensor = field(repr=False)
    scores: torch.Tensor = field(repr=False)
    labels: torch.Tensor = field(repr=False)

    @property
    def max_recall_at_full_precision(self) -> float:
        return self.curve.max_recall_at_full_precision

    def to_dict(self) -> dict[str, object]:
        return {"num_predictions": int(self.pairs.shape[0]), **self.curve.to_dict()}


def _best_per_query(pairs: torch.Tensor, scores: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    s = torch.where(torch.isfinite(scores), scores, torch.full_like(scores, -math.inf))
    # sort by score (desc, stable), then keep each query's first occurrence
    order = torch.argsort(s, descending=True, stable=True)
    q = pairs[order, 0]
    _, first = np.unique(q.numpy(), return_index=True)
    keep = order[torch.from_numpy(first)]
    keep = keep[torch.argsort(pairs[keep, 0])]
    return pairs[keep], scores[keep]


def evaluate_loop_candidates(
    pairs: torch.Tensor,
    scores: torch.Tensor,
    poses: torch.Tensor,
    config: LoopGroundTruthConfig = LoopGroundTruthConfig(),
    indices: torch.Tensor | None = None,
    queries: torch.Tensor | None = None,
) -> LoopEvaluation:
    """Precision/recall of scored loop candidates against the ground truth.

    Args:
        pairs: ``(M, 2)`` int64 frame indices ``(query, candidate)``; of several candidates of one query only
            the highest-scored one is kept.
        scores: ``(M,)`` similarity or verification score (higher = more confident); ``-inf`` / NaN =
            rejected.
        poses: ``(N, 7)`` ground truth per frame (NaN rows: unknown).
        config: the true-loop thresholds.
        indices: frames taking part as queries/database (e.g. keyframes), for the recall denominator.
        queries: ``(Q,)`` the frames that queried, when not all of ``indices`` did: only they count in the
            recall denominator.

    Returns:
        a :class:`LoopEvaluation` with the curve and the labelled predictions.
    """
    poses = _check_poses(poses)
    pairs = torch.as_tensor(pairs, dtype=torch.long).reshape(-1, 2).cpu()
    scores = torch.as_tensor(scores, dtype=torch.float64).flatten().cpu()
    if scores.shape[0] != pairs.shape[0]:
        raise ValueError(f"pairs (M, 2) and scores (M,) disagree: {tuple(pairs.shape)} vs {tuple(scores.shape)}")
    pairs, scores = _best_per_query(pairs, scores)
    labels = is_true_loop(poses, pairs, config).cpu()
    positive = ground_truth_loops(poses, config, indices)[:, 0]
    if queries is not None:
        positive = positive[torch.isin(positive, torch.as_tensor(queries, dtype=torch.long).flatten().cpu())]
    num_positives = int(torch.unique(positive).numel())
    curve = precision_recall_curve(scores, labels, num_positives)
    return LoopEvaluation(curve, pairs, scores, labels)
