"""Loop-closure ground truth, precision/recall and the PR-curve figure."""
from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

from slam.eval.loops import (
    LoopGroundTruthConfig,
    evaluate_loop_candidates,
    ground_truth_loops,
    is_true_loop,
    plot_pr_curves,
    precision_recall_curve,
)
from slam.lie import quat_normalize, quat_to_rotmat, so3_exp


def _pose(x=0.0, yaw_deg=0.0):
    q = so3_exp(torch.tensor([0.0, math.radians(yaw_deg), 0.0], dtype=torch.float64))
    return torch.cat([torch.tensor([x, 0.0, 0.0], dtype=torch.float64), q])


@pytest.fixture
def hand_poses():
    """Frame 0 at the origin; others placed to sit just inside / outside each threshold."""
    poses = torch.full((801, 7), float("nan"), dtype=torch.float64)
    poses[0] = _pose()
    poses[50] = _pose()  # identical but only 50 frames later
    poses[200] = _pose(x=0.49)
    poses[400] = _pose(x=0.51)
    poses[600] = _pose(yaw_deg=44.0)
    poses[800] = _pose(yaw_deg=46.0)
    return poses


def test_is_true_loop_thresholds(hand_poses):
    pairs = torch.tensor([[200, 0], [400, 0], [600, 0], [800, 0], [0, 800], [50, 0], [300, 0], [600, 200]])
    got = is_true_loop(hand_poses, pairs).tolist()
    assert got == [True, False, True, False, False, False, False, True]
    assert is_true_loop(hand_poses, torch.tensor([[50, 0]]), LoopGroundTruthConfig(min_frame_gap=10)).tolist() == [True]
    wide = LoopGroundTruthConfig(max_angle_deg=50)
    assert is_true_loop(hand_poses, torch.tensor([[800, 0]]), wide).tolist() == [True]
    assert is_true_loop(hand_poses, torch.zeros(0, 2, dtype=torch.long)).shape == (0,)
    with pytest.raises(ValueError, match=r"in \[0, 801\)"):
        is_true_loop(hand_poses, torch.tensor([[801, 0]]))
    with pytest.raises(ValueError, match=r"\(N, 7\)"):
        is_true_loop(hand_poses[:, :6], torch.tensor([[1, 0]]))
    with pytest.raises(ValueError):
        LoopGroundTruthConfig(max_distance=-1)


def test_ground_truth_loops_equals_brute_force():
    g = torch.Generator().manual_seed(7)
    n = 160
    steps = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.08
    pos = torch.cumsum(steps, 0)
    pos = pos - pos.mean(0)  # a random walk that wanders back over itself
    q = quat_normalize(torch.cumsum(torch.randn(n, 4, generator=g, dtype=torch.float64) * 0.15, 0) + torch.tensor(
        [0, 0, 0, 1.0], dtype=torch.float64))
    poses = torch.cat([pos, q], -1)
    poses[17] = float("nan")
    cfg = LoopGroundTruthConfig(max_distance=0.3, max_angle_deg=30.0, min_frame_gap=20)
    R = quat_to_rotmat(q).numpy()
    P = pos.numpy()
    expected = []
    for i in range(n):
        for j in range(i - cfg.min_frame_gap + 1):
            if 17 in (i, j):
                continue
            ang = math.degrees(math.acos(np.clip((np.trace(R[i].T @ R[j]) - 1) / 2, -1, 1)))
            if np.linalg.norm(P[i] - P[j]) < cfg.max_distance and ang < cfg.max_angle_deg:
                expected.append([i, j])
    got = ground_truth_loops(poses, cfg)
    assert got.tolist() == expected and len(expected) > 20
    assert torch.equal(ground_truth_loops(poses, cfg, chunk=7), got)
    sub = torch.arange(0, n, 2)
    assert ground_truth_loops(poses, cfg, indices=sub).tolist() == [p for p in expected if p[0] % 2 == 0 == p[1] % 2]
    assert is_true_loop(poses, got, cfg).all()


def test_precision_recall_hand_example():
    scores = torch.tensor([0.9, 0.8, 0.8, 0.5, -math.inf, math.nan], dtype=torch.float64)
    labels = torch.tensor([True, False, True, True, True, False])
    c = precision_recall_curve(scores, labels)  # 4 positives: the -inf one is a loop never detected
    assert c.num_positives == 4
    assert c.recall.tolist() == pytest.approx([0.0, 0.25, 0.5, 0.75])
    assert c.precision.tolist() == pytest.approx([1.0, 1.0, 2 / 3, 0.75])
    assert c.thresholds.tolist() == [math.inf, 0.9, 0.8, 0.5]
    assert c.max_recall_at_full_precision == 0.25 and c.threshold_at_full_precision == 0.9
    assert c.average_precision == pytest.approx(0.25 + 0.25 * 2 / 3 + 0.25 * 0.75)
    # a false positive first: no recall at 100% precision
    c = precision_recall_curve(torch.tensor([0.9, 0.8]), torch.tensor([False, True]), num_positives=5)
    assert c.max_recall_at_full_precision == 0.0 and c.threshold_at_full_precision == math.inf
    assert c.to_dict()["threshold_at_full_precision"] is None
    assert c.recall[-1] == pytest.approx(0.2)
    empty = precision_recall_curve(torch.zeros(0), torch.zeros(0, dtype=torch.bool))
    assert empty.recall.shape == (1,) and empty.max_recall_at_full_precision == 0.0
    with pytest.raises(ValueError, match="num_positives"):
        precision_recall_curve(torch.tensor([0.9, 0.8]), torch.tensor([True, True]), num_positives=1)
    with pytest.raises(ValueError, match="same shape"):
        precision_recall_curve(torch.tensor([0.9]), torch.tensor([True, False]))


def test_evaluate_candidates_best_per_query(hand_poses):
    pairs = torch.tensor([[200, 0], [200, 50], [400, 0], [600, 0], [600, 200], [800, 0]])
    scores = torch.tensor([0.9, 0.95, 0.8, 0.7, 0.2, 0.6], dtype=torch.float64)
    ev = evaluate_loop_candidates(pairs, scores, hand_poses)
    # best per query: 200 -> 50 (0.95, true: 0.49 m, gap 150), 400 -> 0 (false), 600 -> 0 (true), 800 -> 0 (false)
    assert ev.pairs.tolist() == [[200, 50], [400, 0], [600, 0], [800, 0]]
    assert ev.labels.tolist() == [True, False, True, False]
    # queries with an earlier true partner: 200 (0, 50), 400 (200: 0.02 m), 600 (0, 50, 200), 800 (600: 2 deg)
    assert ev.curve.num_positives == 4
    assert ev.max_recall_at_full_precision == 0.25  # 0.95 true, then 0.8 false
    d = ev.to_dict()
    assert d["num_predictions"] == 4 and d["max_recall_at_full_precision"] == 0.25
    assert d["threshold_at_full_precision"] == 0.95 and d["num_positives"] == 4
    json.dumps(d, allow_nan=False)
    # (200, 0), (200, 50), (400, 200), (600, 0), (600, 50), (600, 200), (800, 600)
    assert ground_truth_loops(hand_poses).tolist() == [[200, 0], [200, 50], [400, 200], [600, 0], [600, 50],
                                                        [600, 200], [800, 600]]
    with pytest.raises(ValueError, match="disagree"):
        evaluate_loop_candidates(pairs, scores[:3], hand_poses)
    # 800 did not query (a keyframe that found its loop otherwise): 3 positives, and 200 -> 50 is one of them
    only = evaluate_loop_candidates(pairs[:5], scores[:5], hand_poses, queries=torch.tensor([200, 400, 600]))
    assert only.curve.num_positives == 3 and abs(only.max_recall_at_full_precision - 1 / 3) < 1e-12


def test_redkitchen_revisit_is_a_ground_truth_loop(redkitchen_dir):
    from slam.io import open_sequence

    poses = open_sequence(redkitchen_dir).groundtruth.poses
    pairs = ground_truth_loops(poses)
    revisit = pairs[(pairs[:, 0] >= 940) & (pairs[:, 0] <= 960) & (pairs[:, 1] >= 240) & (pairs[:, 1] <= 270)]
    assert revisit.shape[0] > 50
    d = (poses[revisit[:, 0], :3] - poses[revisit[:, 1], :3]).norm(dim=-1)
    assert float(d.max()) < 0.5
    assert (pairs[:, 0] - pairs[:, 1]).min() >= 100


def test_plot_pr_curves(tmp_path):
    a = precision_recall_curve(torch.tensor([0.9, 0.8, 0.7, 0.6]), torch.tensor([True, True, False, True]))
    b = precision_recall_curve(torch.tensor([0.9, 0.8]), torch.tensor([True, True]), num_positives=3)
    one = plot_pr_curves(tmp_path / "one.png", {"before": a})
    two = plot_pr_curves(tmp_path / "sub" / "two.png", [("before", a), ("after", b)], size=(500, 400))
    assert one.shape == (520, 640, 3) and two.shape == (400, 500, 3) and one.dtype == np.uint8
    assert (tmp_path / "one.png").stat().st_size > 0
    assert np.array_equal(cv2.imread(str(tmp_path / "sub" / "two.png")), two)

    def count(img, rgb):  # matplotlib's first two colours, C0 and C1
        return int((np.abs(img.astype(int) - np.array(rgb[::-1])).sum(-1) < 30).sum())

    c0, c1 = (31, 119, 180), (255, 127, 14)
    assert count(one, c0) > 200 and count(one, c1) == 0
    assert count(two, c1) > 200
    assert plot_pr_curves(None, {}).shape == (520, 640, 3)


def test_loop_recall_keeps_the_frame_gap_in_time_at_any_frame_step():
    """A run on every 6th frame: a revisit 4 s (20 of its frames) after the first view is a true loop,
    as it is at step 1 (120 frames); the 100-frame gap counted in the run's frames would call it none."""
    from types import SimpleNamespace

    from slam.loop.closer import LoopQuery
    from slam.report import loop_ground_truth_for_step, loop_precision_recall

    assert [loop_ground_truth_for_step(s).min_frame_gap for s in (1, 3, 6, 200)] == [100, 34, 17, 1]
    # 21 frames: out along x for 10, stay 1 m away, back at the start at frame 20
    x = [0.1 * k for k in range(11)] + [1.0] * 9 + [0.0]
    gt = torch.stack([_pose(v) for v in x])
    frames = torch.arange(21)
    query = LoopQuery(kf=20, top_kf=0, top_score=0.9, threshold=0.5, candidates=[0], verified=[])
    result = SimpleNamespace(keyframe_frames=frames, queries=[query], loops=[], loop_hypotheses=[])

    def recall(step):
        run = SimpleNamespace(result=result, gt_poses_per_frame=gt, frame_step=step, loop_curves={})
        return loop_precision_recall(run)["before_verification"]

    at6, at1 = recall(6), recall(1)
    assert at6["max_recall_at_full_precision"] == 1.0
    assert at6["num_positives"] == 1  # frame 20, whose match (frames 0-3) is >= 17 frames before it
    assert at1["num_positives"] == 0 and at1["max_recall_at_full_precision"] == 0.0


def test_loop_precision_after_verification_scores_each_pair_with_its_own_similarity():
    """After verification a query proposes its most similar verified candidate, with that pair's own
    similarity, even when the group check later dropped it and kept a less similar loop of the query."""
    from types import SimpleNamespace

    from slam.loop.closer import LoopClosure, LoopQuery
    from slam.report import loop_precision_recall

    # frames 0-2 far apart; frame 3 revisits frame 0, frame 4 is somewhere new
    gt = torch.stack([_pose(v) for v in (0.0, 5.0, 9.0, 0.05, 20.0)])
    frames = torch.arange(5)

    def loop(a, b, sim):
        return LoopClosure(a, b, a, b, float(a), float(b), sim, 100, torch.zeros(7, dtype=torch.float64))

    q3 = LoopQuery(kf=3, top_kf=0, top_score=0.95, threshold=0.4, candidates=[0, 1], verified=[0, 1])
    q4 = LoopQuery(kf=4, top_kf=2, top_score=0.7, threshold=0.4, candidates=[2], verified=[2])
    true_dropped, false_kept, false_4 = loop(0, 3, 0.95), loop(1, 3, 0.5), loop(2, 4, 0.7)
    result = SimpleNamespace(keyframe_frames=frames, queries=[q3, q4], loops=[false_kept, false_4],
                             loop_hypotheses=[true_dropped, false_kept, false_4])
    run = SimpleNamespace(result=result, gt_poses_per_frame=gt, frame_step=1, loop_curves={})
    after = loop_precision_recall(run, LoopGroundTruthConfig(min_frame_gap=2))["after_verification"]
    # (3, 0) at 0.95 is ranked first and is true: recall 1 at full precision (scored 0.5, it fell below (4, 2))
    assert after["num_positives"] == 1 and after["max_recall_at_full_precision"] == 1.0
