"""Timestamp association (evo's nearest-neighbour rule by default, TUM's greedy rule on request) and RPE
pairs in seconds, on hand-computed cases (no evo needed; the comparison with evo is in
tests/slam/eval/test_eval_metrics.py). Stamps are binary fractions where a boundary is tested, so that the
differences are exact."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from slam.eval import associate, associate_nearest, associate_trajectories, ate, rpe
from slam.io.trajectory import Trajectory


def _traj(stamps, x=None) -> Trajectory:
    t = torch.tensor(stamps, dtype=torch.float64)
    poses = torch.zeros(len(stamps), 7, dtype=torch.float64)
    poses[:, 6] = 1.0
    poses[:, 0] = t if x is None else torch.tensor(x, dtype=torch.float64)
    poses[:, 1] = t * t  # not collinear, so that an SE(3) alignment is defined
    return Trajectory(t, poses)


def test_nearest_rule_closed_boundary_where_tum_is_strict():
    ref = [0.5, 1.5, 2.5]
    est = [0.515625, 1.515625, 2.515625]  # exactly 2^-6 s late
    i, j = associate_nearest(ref, est, max_difference=0.015625)
    assert i.tolist() == [0, 1, 2] and j.tolist() == [0, 1, 2]  # evo: |dt| <= max_diff
    assert associate(ref, est, max_difference=0.015625)[0].numel() == 0  # TUM: |dt| < max_difference
    assert ate(_traj(ref), _traj(est), max_difference=0.015625, alignment="none").num_pairs == 3
    with pytest.raises(ValueError, match="within 0.015625 s"):
        ate(_traj(ref), _traj(est), max_difference=0.015625, alignment="none", association="tum")
    assert associate_nearest(ref, est, max_difference=0.0156249)[0].numel() == 0


def test_nearest_rule_starts_from_the_shorter_list_the_estimate_on_equal_lengths():
    # equal lengths: evo starts from the second list (the estimate); 0.005 is nearer 0.009 than 0.0
    i, j = associate_nearest([0.0, 0.009, 1.0], [0.005, 1.0, 2.0])
    assert i.tolist() == [1, 2] and j.tolist() == [0, 1]
    # the reference shorter: each of its stamps takes its nearest estimate stamp, shared (not one-to-one)
    i, j = associate_nearest([0.0, 0.009], [0.005, 1.0, 2.0])
    assert i.tolist() == [0, 1] and j.tolist() == [0, 0]
    # the estimate shorter
    i, j = associate_nearest([0.0, 0.009, 1.0, 2.0, 3.0], [0.005, 0.006])
    assert i.tolist() == [1, 1] and j.tolist() == [0, 1]


def test_nearest_rule_ties_order_and_offset():
    # a tie (0.5 from both) goes to the earlier stamp, as evo's `diff_lb <= diff_ub`
    assert [x.tolist() for x in associate_nearest([0.0, 1.0], [0.5], max_difference=0.5)] == [[0], [0]]
    assert [x.tolist() for x in associate_nearest([0.5], [0.0, 1.0], max_difference=0.5)] == [[0], [0]]
    # unsorted long list: evo's linear search, first minimum
    assert [x.tolist() for x in associate_nearest([1.0, 0.0], [0.5], max_difference=0.5)] == [[0], [0]]
    # the pairs follow the shorter list (here the estimate, unsorted); the offset is added to the estimate
    i, j = associate_nearest([0.0, 1.0, 2.0, 3.0], [1.25, 0.25, 3.25], offset=-0.25)
    assert i.tolist() == [1, 0, 3] and j.tolist() == [0, 1, 2]
    # TUM's greedy one-to-one rule crosses pairs where the nearest rule does not
    i, j = associate([0.0, 0.010], [0.009, 0.015])
    assert i.tolist() == [0, 1] and j.tolist() == [1, 0]
    i, j = associate_nearest([0.0, 0.010], [0.009, 0.015])
    assert i.tolist() == [1, 1] and j.tolist() == [0, 1]
    assert associate_nearest([], [1.0])[0].shape == (0,)
    with pytest.raises(ValueError, match="max_difference"):
        associate_nearest([0.0], [0.0], max_difference=float("nan"))


def test_association_option_of_ate_rpe_and_trajectories():
    ref, est = _traj([0.0, 0.010, 1.0, 2.0, 3.0]), _traj([0.009, 0.015, 1.0, 2.0, 3.0])
    r, e = associate_trajectories(ref, est)
    assert r.timestamps.tolist() == [0.010, 0.010, 1.0, 2.0, 3.0] and e.timestamps.tolist() == est.timestamps.tolist()
    r, e = associate_trajectories(ref, est, association="tum")
    assert r.timestamps.tolist() == ref.timestamps.tolist() and e.timestamps.tolist() == [0.015, 0.009, 1.0, 2.0, 3.0]
    r = ate(ref, est, alignment="none")
    assert r.timestamps.tolist() == [0.010, 0.010, 1.0, 2.0, 3.0]
    assert r.estimate_aligned.timestamps.tolist() == est.timestamps.tolist()
    r = ate(ref, est, alignment="none", association="tum")
    assert r.timestamps.tolist() == ref.timestamps.tolist() and r.num_pairs == 5
    assert r.estimate_aligned.timestamps.tolist() == [0.015, 0.009, 1.0, 2.0, 3.0]
    with pytest.raises(ValueError, match="association must be one of"):
        ate(ref, est, association="greedy")
    with pytest.raises(ValueError, match="association must be one of"):
        rpe(ref, est, association="nearest")


def test_rpe_seconds_on_crossing_tum_pairs_uses_time_order():
    """TUM's rule pairs (0.0, 0.015) and (0.010, 0.009): the estimate's associated stamps are not sorted."""
    ref, est = _traj([0.0, 0.010, 1.0, 2.0, 3.0]), _traj([0.009, 0.015, 1.0, 2.0, 3.0])
    res = rpe(ref, est, delta=1.0, delta_unit="seconds", all_pairs=True, association="tum")
    assert res.pairs.tolist() == [[1, 2], [0, 2], [2, 3], [3, 4]]
    assert res.timestamps.tolist() == [[0.009, 1.0], [0.015, 1.0], [1.0, 2.0], [2.0, 3.0]]
    res = rpe(ref, est, delta=1.0, delta_unit="seconds", association="tum")
    assert res.pairs.tolist() == [[1, 2], [2, 3], [3, 4]]


def test_rpe_seconds_consecutive_pairs_resume_after_a_gap():
    """4 Hz for 2 s, a gap of 3.25 s, 4 Hz for 3 s; the estimate drifts 10 %: every pair 1 s apart errs 0.1 m."""
    t = [k * 0.25 for k in range(8)] + [5.0 + k * 0.25 for k in range(12)]
    ref, est = _traj(t), _traj(t, x=[1.1 * s for s in t])
    res = rpe(ref, est, delta=1.0, delta_unit="seconds")
    # 0 -> 1.0; 1.0's target 2.0 is in the gap (nearest 1.75, beyond half a frame): no pair, on to 1.75;
    # 1.75 has no later partner: on to the next pose, 5.0 -> 6.0 -> 7.0; 7.0's target is past the end.
    assert res.timestamps.tolist() == [[0.0, 1.0], [5.0, 6.0], [6.0, 7.0]]
    assert res.pairs.tolist() == [[0, 4], [8, 12], [12, 16]]
    assert res.trans_errors.tolist() == pytest.approx([0.1] * 3, abs=1e-12)
    res = rpe(ref, est, delta=1.0, delta_unit="seconds", all_pairs=True)
    starts = [0.0, 0.25, 0.5, 0.75] + [5.0 + k * 0.25 for k in range(8)]
    assert res.timestamps[:, 0].tolist() == starts and res.timestamps[:, 1].tolist() == [s + 1.0 for s in starts]
    # a gap-free stream is unchanged: consecutive pairs 0 -> 1 -> 2 ... as before
    u = [k * 0.25 for k in range(20)]
    res = rpe(_traj(u), _traj(u, x=[1.1 * s for s in u]), delta=1.0, delta_unit="seconds")
    assert res.pairs.tolist() == [[0, 4], [4, 8], [8, 12], [12, 16]]
    assert np.allclose(res.trans_errors.numpy(), 0.1, atol=1e-12)
