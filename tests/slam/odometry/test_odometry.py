"""Features, matching, registration and the odometry front end: synthetic planar scenes and real 7-Scenes frames.

The real-data tests read the shared redkitchen sequence through a small private loader
(``_load_7scenes_frame``) until the project's dataset reader is used here.
"""
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from slam.io.frame import RGBDFrame
from slam.lie import se3_between, se3_exp, se3_from_matrix, se3_identity, se3_inv, se3_log
from slam.odometry import (
    FeatureConfig,
    MatchConfig,
    OdometryConfig,
    RGBDOdometry,
    TrackStatus,
    extract_features,
    match_features,
    register,
)
from slam.odometry.matching import hamming_distance, unpack_bits

K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------------------------
# data
# ----------------------------------------------------------------------------------------------
def _load_7scenes_frame(folder: Path, i: int) -> RGBDFrame:
    """Frame ``i`` of a 7-Scenes folder (cv2 reads BGR; depth mm, 0 and 65535 invalid)."""
    stem = folder / f"frame-{i:06d}"
    bgr = cv2.imread(str(stem) + ".color.jpg", cv2.IMREAD_COLOR)
    raw = cv2.imread(str(stem) + ".depth.png", cv2.IMREAD_UNCHANGED)
    depth = np.where(raw == 65535, 0, raw).astype(np.float32) / 1000.0
    T = np.loadtxt(str(stem) + ".pose.txt")
    pose = se3_from_matrix(torch.from_numpy(T)).numpy()
    return RGBDFrame(i, i / 30.0, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth, K.copy(), pose)


def _texture(seed: int = 0, size=(960, 1280)) -> np.ndarray:
    """A random multi-scale texture (ORB needs corners at several scales)."""
    rng = np.random.default_rng(seed)
    img = np.zeros(size, np.float32)
    for s in (4, 16, 64):
        small = rng.random((size[0] // s, size[1] // s)).astype(np.float32)
        img += cv2.resize(small, (size[1], size[0]), interpolation=cv2.INTER_CUBIC)
    img = (img - img.min()) / (img.max() - img.min()) * 255
    return img.astype(np.uint8)


def _planar_frame(T_wc: np.ndarray, texture: np.ndarray, index: int = 0, plane_z: float = 2.0) -> RGBDFrame:
    """Render a textured plane ``z = plane_z`` (world frame) seen from camera pose ``T_wc`` (7,)."""
    T = se3_to_np(T_wc)
    R, t = T[:3, :3], T[:3, 3]
    H_img, W_img = 480, 640
    u, v = np.meshgrid(np.arange(W_img, dtype=np.float64), np.arange(H_img, dtype=np.float64))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    rays_w = rays @ R.T
    s = (plane_z - t[2]) / rays_w[..., 2]  # the depth along the camera z axis (rays have z = 1)
    Xw = t + s[..., None] * rays_w
    # texture coordinates: 1 texel = 2.5 mm, texture centred on the world origin
    mx = (Xw[..., 0] / 0.0025 + texture.shape[1] / 2).astype(np.float32)
    my = (Xw[..., 1] / 0.0025 + texture.shape[0] / 2).astype(np.float32)
    gray = cv2.remap(texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    rgb = np.repeat(gray[..., None], 3, axis=2)
    return RGBDFrame(index, index / 30.0, rgb, s.astype(np.float32), K.copy(), T_wc.copy())


def se3_to_np(pose: np.ndarray) -> np.ndarray:
    from slam.lie import se3_to_matrix
    return se3_to_matrix(torch.as_tensor(pose, dtype=torch.float64)).numpy()


def _pose(tx=0.0, ty=0.0, tz=0.0, rx=0.0, ry=0.0, rz=0.0) -> np.ndarray:
    return se3_exp(torch.tensor([tx, ty, tz, rx, ry, rz], dtype=torch.float64)).numpy()


def _err(T_est: torch.Tensor, T_true) -> tuple:
    e = se3_log(se3_between(torch.as_tensor(T_true, dtype=torch.float64), T_est))
    return float(e[:3].norm()), float(np.degrees(float(e[3:].norm())))


# ----------------------------------------------------------------------------------------------
# features and matching
# ----------------------------------------------------------------------------------------------
def test_features_are_spread_and_backprojected():
    f = _planar_frame(_pose(), _texture())
    feats = extract_features(f.rgb, f.depth, f.K)
    n = len(feats)
    assert 500 <= n <= 1000  # capped by max_features
    assert feats.descriptors.shape == (n, 32) and feats.descriptors.dtype == torch.uint8
    assert feats.num_valid > 0.9 * n
    # every back-projected point lies on the plane z = 2
    assert torch.allclose(feats.points[feats.valid][:, 2], torch.tensor(2.0), atol=1e-5)
    # bucketing: every cell of the 6x8 grid has keypoints
    cx = (feats.keypoints[:, 0] * 8 / 640).long().clamp(max=7)
    cy = (feats.keypoints[:, 1] * 6 / 480).long().clamp(max=5)
    assert len(set((cy * 8 + cx).tolist())) == 48


def test_feature_errors_and_empty_image():
    with pytest.raises(ValueError, match="rgb"):
        extract_features(np.zeros((4, 4), np.uint8), np.zeros((4, 4), np.float32), K)
    with pytest.raises(ValueError, match="depth"):
        extract_features(np.zeros((4, 4, 3), np.uint8), np.zeros((5, 4), np.float32), K)
    f = extract_features(np.zeros((480, 640, 3), np.uint8), np.ones((480, 640), np.float32), K)
    assert len(f) == 0 and f.points.shape == (0, 3) and f.valid.shape == (0,)


def test_rgb_intrinsics_lift_keypoints_in_the_colour_camera():
    f = _planar_frame(_pose(), _texture())  # fronto-parallel plane at z = 2 m
    base = extract_features(f.rgb, f.depth, f.K)
    cfg = FeatureConfig(rgb_intrinsics=(525.0, 520.0, 310.0, 250.0), rgb_from_depth_translation=(-0.025, 0.0, 0.0))
    lifted = extract_features(f.rgb, f.depth, f.K, cfg)
    # keypoints stay colour pixels, K becomes the colour camera's
    assert torch.allclose(lifted.keypoints, base.keypoints)
    K = torch.tensor([[525.0, 0, 310.0], [0, 520.0, 250.0], [0, 0, 1]], dtype=torch.float64)
    assert torch.allclose(lifted.K, K)
    # the plane z = 2 stays z = 2 after a sideways shift: points are z * K_rgb^-1 [u, v, 1]
    v = lifted.valid
    assert v.sum() > 0.8 * base.valid.sum()
    kp, pts = lifted.keypoints[v].double(), lifted.points[v].double()
    assert torch.allclose(pts[:, 2], torch.tensor(2.0, dtype=torch.float64), atol=1e-5)
    assert torch.allclose(pts[:, 0], (kp[:, 0] - 310.0) / 525.0 * 2.0, atol=1e-4)
    assert torch.allclose(pts[:, 1], (kp[:, 1] - 250.0) / 520.0 * 2.0, atol=1e-4)


def test_hamming_distance_dense_sparse_and_bits():
    g = torch.Generator().manual_seed(0)
    a = torch.randint(0, 256, (7, 32), generator=g, dtype=torch.uint8)
    b = torch.randint(0, 256, (5, 32), generator=g, dtype=torch.uint8)
    ref = torch.tensor([[sum(bin(int(x) ^ int(y)).count("1") for x, y in zip(ra, rb)) for rb in b]
                        for ra in a], dtype=torch.float32)
    assert torch.equal(hamming_distance(a, b), ref)
    pairs = torch.tensor([[0, 0], [6, 4], [3, 2]])
    assert torch.equal(hamming_distance(a, b, pairs), ref[pairs[:, 0], pairs[:, 1]])
    # squared L2 of the unpacked bits equals the Hamming distance
    assert torch.allclose(torch.cdist(unpack_bits(a), unpack_bits(b)) ** 2, ref, atol=1e-3)
    # a keyframe's size (the matmul's blocked kernels), against numpy's bit unpacking
    a, b = (torch.randint(0, 256, (n, 32), generator=g, dtype=torch.uint8) for n in (1000, 900))
    bits_a, bits_b = (np.unpackbits(x.numpy(), axis=1).astype(np.int64) for x in (a, b))
    ref = (bits_a[:, None, :] != bits_b[None, :, :]).sum(-1)
    assert np.array_equal(hamming_distance(a, b).numpy(), ref.astype(np.float32))


@pytest.mark.parametrize("method", ["smnn", "snn", "mnn"])
def test_matching_finds_true_correspondences(method):
    tex = _texture()
    fa_ = _planar_frame(_pose(), tex)
    T_ab = _pose(0.05, -0.02, 0.03, 0.02, 0.03, -0.01)
    fb_ = _planar_frame(T_ab, tex)  # world = frame a
    fa = extract_features(fa_.rgb, fa_.depth, K)
    fb = extract_features(fb_.rgb, fb_.depth, K)
    idx, dist = match_features(fa, fb, MatchConfig(method=method))
    assert idx.shape[1] == 2 and idx.shape[0] == dist.shape[0] > 100
    # a correct match: b's point mapped into a lands on a's point
    from slam.odometry.geometry import transform_points
    pa = fa.points[idx[:, 0]].double()
    pb = transform_points(torch.from_numpy(T_ab), fb.points[idx[:, 1]].double())
    correct = ((pa - pb).norm(dim=-1) < 0.02).float().mean()
    assert correct > 0.8


# ----------------------------------------------------------------------------------------------
# registration on synthetic planes (exact ground truth)
# ----------------------------------------------------------------------------------------------
def test_register_recovers_synthetic_motion_with_and_without_prior():
    tex = _texture(1)
    a = _planar_frame(_pose(), tex)
    T_ab = _pose(0.08, 0.03, -0.05, 0.03, -0.05, 0.02)
    b = _planar_frame(T_ab, tex)
    fa = extract_features(a.rgb, a.depth, K)
    fb = extract_features(b.rgb, b.depth, K)
    for prior in (None, torch.from_numpy(T_ab), se3_identity(dtype=torch.float64)):
        res = register(fa, fb, prior_ab=prior)
        assert res.success, res.reason
        t_err, r_err = _err(res.T_ab, T_ab)
        assert t_err < 0.005 and r_err < 0.3, (t_err, r_err)
        assert res.num_inliers > 100 and res.inlier_rmse < 0.01
        assert res.matches.shape == (res.num_matches, 2) and int(res.inliers.sum()) == res.num_inliers
        H = res.information
        assert torch.allclose(H, H.T) and float(torch.linalg.eigvalsh(H).min()) > 0
    # swapping the frames gives the inverse
    back = register(fb, fa)
    assert back.success
    t_err, r_err = _err(back.T_ab, se3_inv(torch.from_numpy(T_ab)).numpy())
    assert t_err < 0.005 and r_err < 0.3


def test_register_failures_are_results_not_exceptions():
    tex = _texture(2)
    a = _planar_frame(_pose(), tex)
    fa = extract_features(a.rgb, a.depth, K)
    # a different texture: nothing matches geometrically
    c = _planar_frame(_pose(), _texture(99))
    fc = extract_features(c.rgb, c.depth, K)
    res = register(fa, fc)
    assert not res.success and res.reason and res.T_ab.shape == (7,)
    # no depth at all
    fz = extract_features(a.rgb, np.zeros_like(a.depth), K)
    res = register(fa, fz)
    assert not res.success and "valid depth" in res.reason


# ----------------------------------------------------------------------------------------------
# front end
# ----------------------------------------------------------------------------------------------
def test_frontend_tracks_a_synthetic_trajectory_with_keyframes_and_edges():
    tex = _texture(3)
    cfg = OdometryConfig(keyframe_translation=0.05)
    odo = RGBDOdometry(cfg)
    poses = [_pose(0.012 * i, 0.004 * i, 0.0, 0.0, 0.004 * i, 0.002 * i) for i in range(12)]
    results = [odo.track(_planar_frame(p, tex, i)) for i, p in enumerate(poses)]
    assert results[0].status is TrackStatus.INITIALIZED and results[0].is_keyframe
    assert all(r.status is TrackStatus.OK for r in results[1:]), [r.reason for r in results]
    # the registration that placed each frame: exact synthetic depth -> sub-centimetre inlier residuals
    assert math.isnan(results[0].inlier_rmse) and results[0].num_inliers == 0
    assert all(0.0 < r.inlier_rmse < 0.01 and r.num_inliers > 100 for r in results[1:])
    for r, p in zip(results, poses):  # world = the first camera (identity here)
        t_err, r_err = _err(r.pose, p)
        assert t_err < 0.01 and r_err < 0.5
    assert len(odo.keyframes) >= 3  # 0.132 m in total with keyframes every 0.05 m
    edges = [r.edge for r in results if r.edge is not None]
    assert len(edges) == len(odo.keyframes) - 1 == len(odo.edges)
    for e in edges:  # an edge is the relative pose of its two keyframes
        rel = se3_between(odo.keyframes[e.i].pose, odo.keyframes[e.j].pose)
        assert se3_log(se3_between(rel, e.T_ij)).abs().max() < 1e-9
        assert e.information.shape == (6, 6) and not e.weak
    for r in results:  # pose = keyframe pose * T_kf_frame
        kf = odo.keyframes[r.keyframe_id]
        from slam.lie import se3_compose
        assert se3_log(se3_between(se3_compose(kf.pose, r.T_kf_frame), r.pose)).abs().max() < 1e-9
    assert odo.keyframes[0].rgb.shape == (240, 320, 3)  # stored at half size


def test_frontend_with_sift_features_tracks_the_synthetic_trajectory():
    # OdometryConfig(features=FeatureConfig(detector="sift")): float RootSIFT descriptors matched by L2
    tex = _texture(3)
    odo = RGBDOdometry(OdometryConfig(features=FeatureConfig(detector="sift"), keyframe_translation=0.05))
    poses = [_pose(0.015 * i, 0.005 * i, 0.0, 0.0, 0.005 * i, 0.002 * i) for i in range(4)]
    results = [odo.track(_planar_frame(p, tex, i)) for i, p in enumerate(poses)]
    assert all(r.status in (TrackStatus.OK, TrackStatus.INITIALIZED) for r in results), [r.reason for r in results]
    assert not odo.keyframes[0].features.binary and odo.keyframes[0].features.descriptors.shape[1] == 128
    for r, p in zip(results, poses):
        t_err, r_err = _err(r.pose, p)
        assert t_err < 0.01 and r_err < 0.5


def test_frontend_bad_frames_are_lost_then_recovered_and_forced_keyframe():
    tex = _texture(4)
    odo = RGBDOdometry(OdometryConfig(max_lost_frames=3))
    black = RGBDFrame(0, 0.0, np.zeros((480, 640, 3), np.uint8), np.ones((480, 640), np.float32), K)
    r = odo.track(black)  # before initialisation
    assert r.status is TrackStatus.LOST and r.keyframe_id == -1 and "valid depth" in r.reason
    assert torch.equal(r.pose, se3_identity(dtype=torch.float64))
    poses = [_pose(0.01 * i) for i in range(10)]
    assert odo.track(_planar_frame(poses[0], tex, 1)).status is TrackStatus.INITIALIZED
    assert odo.track(_planar_frame(poses[1], tex, 2)).status is TrackStatus.OK
    good = _planar_frame(poses[2], tex, 3)
    no_depth = RGBDFrame(3, 0.1, good.rgb, np.zeros_like(good.depth), K)
    r = odo.track(no_depth)
    assert r.status is TrackStatus.LOST and "valid depth" in r.reason
    assert math.isnan(r.inlier_rmse) and r.num_inliers == 0
    # constant velocity: 1 cm per frame along x
    assert abs(float(r.pose[0]) - 0.02) < 0.003
    wrong_shape = RGBDFrame(4, 0.13, np.zeros((10, 10, 3), np.uint8), np.zeros((10, 10), np.float32), K)
    wrong_shape.rgb = wrong_shape.rgb[..., 0]  # changed after the checks of the constructor
    r = odo.track(wrong_shape)
    assert r.status is TrackStatus.LOST and "unusable frame" in r.reason
    r = odo.track(_planar_frame(poses[4], tex, 5))
    assert r.status is TrackStatus.RECOVERED, r.reason
    assert _err(r.pose, poses[4])[0] < 0.01
    # three frames of another scene in a row: the first promotes the last tracked frame to a keyframe
    # and fails against it too; after the third a keyframe is forced with a weak edge
    other = _texture(50)
    n_kf = len(odo.keyframes)
    out = [odo.track(_planar_frame(poses[5 + k], other, 6 + k)) for k in range(3)]
    assert all(o.status is TrackStatus.LOST for o in out)
    assert out[-1].is_keyframe and out[-1].edge is not None and out[-1].edge.weak
    assert "promoted" in out[0].reason and out[0].edge is not None and not out[0].edge.weak
    assert len(odo.keyframes) == n_kf + 2 and odo.keyframes[-2].frame_index == 5
    assert float(out[-1].edge.information.max()) <= OdometryConfig().weak_edge_information
    # tracking restarts against the forced keyframe
    r = odo.track(_planar_frame(poses[8], other, 9))
    assert r.status is TrackStatus.RECOVERED and r.keyframe_id == out[-1].edge.j, r.reason


# ----------------------------------------------------------------------------------------------
# real frames (shared 7-Scenes redkitchen)
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("i,k,t_tol,r_tol", [(0, 1, 0.01, 0.5), (100, 5, 0.015, 1.0), (300, 10, 0.015, 1.0),
                                              (500, 20, 0.03, 1.5)])
def test_register_real_frames_against_ground_truth(redkitchen_dir, i, k, t_tol, r_tol):
    """Tolerances: the ground truth itself (KinectFusion) is accurate to ~1-2 cm."""
    a, b = _load_7scenes_frame(redkitchen_dir, i), _load_7scenes_frame(redkitchen_dir, i + k)
    fa = extract_features(a.rgb, a.depth, a.K)
    fb = extract_features(b.rgb, b.depth, b.K)
    res = register(fa, fb)
    assert res.success, res.reason
    gt = se3_between(torch.from_numpy(a.pose_gt), torch.from_numpy(b.pose_gt))
    t_err, r_err = _err(res.T_ab, gt.numpy())
    assert t_err < t_tol and r_err < r_tol, (t_err, r_err)


def test_frontend_on_real_consecutive_frames(redkitchen_dir):
    odo = RGBDOdometry()
    frames = [_load_7scenes_frame(redkitchen_dir, i) for i in range(200, 240)]
    results = [odo.track(f) for f in frames]
    assert all(r.status in (TrackStatus.OK, TrackStatus.INITIALIZED) for r in results)
    gt0 = torch.from_numpy(frames[0].pose_gt)
    for r, f in zip(results[5::5], frames[5::5]):
        gt = se3_between(gt0, torch.from_numpy(f.pose_gt))
        t_err, r_err = _err(r.pose, gt.numpy())
        assert t_err < 0.03 and r_err < 1.5, (f.index, t_err, r_err)
    # a black image and a zero-depth frame are LOST, not a crash, and tracking resumes
    f = frames[-1]
    black = RGBDFrame(240, 8.0, np.zeros_like(f.rgb), f.depth, K)
    assert odo.track(black).status is TrackStatus.LOST
    zero = RGBDFrame(241, 8.03, f.rgb, np.zeros_like(f.depth), K)
    assert odo.track(zero).status is TrackStatus.LOST
    nxt = _load_7scenes_frame(redkitchen_dir, 242)
    r = odo.track(nxt)
    assert r.status is TrackStatus.RECOVERED, r.reason
    gt = se3_between(gt0, torch.from_numpy(nxt.pose_gt))
    assert _err(r.pose, gt.numpy())[0] < 0.04
