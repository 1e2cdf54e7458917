"""slam.odometry's edge cases that used to give wrong results (each case failed before its fix).

Every expected value is hand-computed or comes from an independent reference (Kornia's dense matcher on
the full Hamming matrix), never from the code under test.
"""
import math

import kornia.feature as KF
import pytest
import torch

from slam.odometry.config import MatchConfig, RansacConfig
from slam.odometry.features import FrameFeatures
from slam.odometry.geometry import backproject
from slam.odometry.matching import hamming_distance, match_descriptors, match_features
from slam.odometry.ransac import ransac_rigid, refine_rigid

# fx = fy = 100, cx = 2, cy = 1.5 (pixel centres at integer coordinates, the OpenCV convention)
K = torch.tensor([[100.0, 0.0, 2.0], [0.0, 100.0, 1.5], [0.0, 0.0, 1.0]], dtype=torch.float64)


# ----------------------------------------------------------------------------------------------
# back-projection
# ----------------------------------------------------------------------------------------------
def test_backproject_hand_case_unchanged():
    """A valid keypoint: x = (u - cx) / fx * z, y = (v - cy) / fy * z (hand-computed)."""
    depth = torch.full((4, 5), 2.0, dtype=torch.float64)
    pts, ok = backproject(torch.tensor([[3.0, 2.0]]), depth, K, window_radius=1)
    assert ok.tolist() == [True]
    torch.testing.assert_close(pts, torch.tensor([[0.02, 0.01, 2.0]], dtype=torch.float64), rtol=0, atol=1e-15)


def test_backproject_zero_depth_is_invalid_with_min_depth_zero():
    """``min_depth=0`` must not turn a zero (= invalid) depth into a valid point at the camera centre."""
    depth = torch.zeros(4, 5)
    depth[1, 3] = 1.0
    kp = torch.tensor([[2.0, 1.0], [3.0, 1.0]])
    pts, ok = backproject(kp, depth, K, min_depth=0.0, window_radius=0)
    assert ok.tolist() == [False, True]
    assert pts[0].tolist() == [0.0, 0.0, 0.0]
    torch.testing.assert_close(pts[1], torch.tensor([0.01, -0.005, 1.0]), rtol=0, atol=1e-7)


def test_backproject_infinite_depth_is_invalid():
    """``max_depth=inf`` (allowed: no upper bound) must not accept an inf pixel as a point at ~3e38 m, and an
    inf neighbour must fail the window check even with ``max_depth_jump=inf``."""
    depth = torch.full((4, 5), 2.0)
    depth[1, 2] = math.inf
    pts, ok = backproject(torch.tensor([[2.0, 1.0]]), depth, K, min_depth=0.0, max_depth=math.inf,
                          window_radius=0)
    assert ok.tolist() == [False] and pts.tolist() == [[0.0, 0.0, 0.0]]
    # keypoint (2, 2) has depth 2 but its 3x3 window holds the inf pixel (2, 1)
    pts, ok = backproject(torch.tensor([[2.0, 2.0], [3.0, 2.0]]), depth, K, max_depth=math.inf,
                          window_radius=1, max_depth_jump=math.inf)
    assert ok.tolist() == [False, False]  # (3, 2)'s window also touches (2, 1)
    depth[1, 2] = -math.inf
    pts, ok = backproject(torch.tensor([[2.0, 1.0]]), depth, K, min_depth=0.0, window_radius=0)
    assert ok.tolist() == [False]


def test_backproject_nonfinite_keypoint_gives_zero_point():
    """A NaN / inf keypoint is invalid and its point is zeros (it used to be NaN: NaN * 0), the others are
    unaffected."""
    depth = torch.full((4, 5), 2.0, dtype=torch.float64)
    kp = torch.tensor([[math.nan, 2.0], [3.0, 2.0], [math.inf, 1.0], [2.0, -math.inf]], dtype=torch.float64)
    pts, ok = backproject(kp, depth, K, window_radius=0)
    assert ok.tolist() == [False, True, False, False]
    assert torch.isfinite(pts).all()
    assert pts[[0, 2, 3]].abs().sum().item() == 0.0
    torch.testing.assert_close(pts[1], torch.tensor([0.02, 0.01, 2.0], dtype=torch.float64), rtol=0, atol=1e-15)


# ----------------------------------------------------------------------------------------------
# RANSAC argument checks
# ----------------------------------------------------------------------------------------------
def _cloud(n=30, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g, dtype=torch.float64) + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


@pytest.mark.parametrize("bad", [0.0, -0.01, math.nan])
def test_ransac_rejects_nonpositive_or_nan_thresholds(bad):
    """A zero threshold divided the MSAC cost by zero and NaN / negative ones were reported as "degenerate"
    geometry: a wrong argument is now a ValueError naming it."""
    src = _cloud()
    thr = torch.full((30,), 0.03, dtype=torch.float64)
    thr[5] = bad
    with pytest.raises(ValueError, match="thresholds"):
        ransac_rigid(src, src + 0.1, thresholds=thr)


def test_ransac_infinite_threshold_still_allowed():
    """``inf`` switches the inlier bound off (RansacConfig.inlier_threshold = inf is valid): no error, all inliers."""
    src = _cloud()
    res = ransac_rigid(src, src + 0.1, RansacConfig(refine_iterations=0),
                       thresholds=torch.full((30,), math.inf, dtype=torch.float64))
    assert res.num_inliers == 30


def test_ransac_and_refine_check_covariance_shapes():
    src = _cloud()
    bad = torch.eye(3, dtype=torch.float64).expand(5, 3, 3)
    with pytest.raises(ValueError, match=r"cov_src must have shape \(30, 3, 3\)"):
        ransac_rigid(src, src + 0.1, cov_src=bad, cov_dst=bad)
    good = 1e-4 * torch.eye(3, dtype=torch.float64).expand(30, 3, 3)
    with pytest.raises(ValueError, match="cov_dst"):
        ransac_rigid(src, src + 0.1, cov_src=good, cov_dst=bad)
    pose = torch.tensor([0.1, 0.1, 0.1, 0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    with pytest.raises(ValueError, match="cov_dst"):
        refine_rigid(pose, src, src + 0.1, good, bad)
    with pytest.raises(ValueError, match="src and dst"):
        refine_rigid(pose, src, (src + 0.1)[:29], good, good)
    with pytest.raises(ValueError, match="pose"):
        refine_rigid(pose[:6], src, src + 0.1, good, good)
    # the hand case: a pure translation is recovered exactly
    out, _ = refine_rigid(torch.tensor([0.0, 0, 0, 0, 0, 0, 1], dtype=torch.float64), src, src + 0.1, good, good)
    torch.testing.assert_close(out, pose, rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------------------------
# matching with a single descriptor
# ----------------------------------------------------------------------------------------------
def _kornia_reference(da, db, method, ratio=0.9):
    dm = hamming_distance(da, db)
    if method == "mnn":
        _, idx = KF.match_mnn(da, db, dm=dm)
    elif method == "snn":
        _, idx = KF.match_snn(da, db, ratio, dm=dm)
    else:
        _, idx = KF.match_smnn(da, db, ratio, dm=dm)
    return idx.tolist()


@pytest.mark.parametrize("method", ["mnn", "snn", "smnn"])
def test_single_descriptor_matches_like_kornia(method):
    """A frame with one descriptor used to get no match at all; mnn (and snn from the single side) have a
    well-defined answer: Kornia's on the full Hamming matrix."""
    g = torch.Generator().manual_seed(3)
    b = torch.randint(0, 256, (6, 32), generator=g, dtype=torch.uint8)
    a = b[2:3].clone()
    a[0, 0] ^= 1  # one bit away from b[2]
    cfg = MatchConfig(method=method)
    for da, db in ((a, b), (b, a)):
        idx, dist = match_descriptors(da, db, True, cfg)
        assert idx.tolist() == _kornia_reference(da, db, method)
        assert dist.tolist() == [1.0] * idx.shape[0]
    if method == "mnn":  # hand check: the one-bit-away descriptor is the mutual nearest neighbour
        assert match_descriptors(a, b, True, cfg)[0].tolist() == [[0, 2]]
        assert match_descriptors(b, a, True, cfg)[0].tolist() == [[2, 0]]


@pytest.mark.parametrize("method", ["mnn", "snn", "smnn"])
def test_zero_descriptors_give_empty_matches(method):
    b = torch.randint(0, 256, (6, 32), dtype=torch.uint8)
    e = torch.zeros(0, 32, dtype=torch.uint8)
    for da, db in ((e, b), (b, e), (e, e)):
        idx, dist = match_descriptors(da, db, True, MatchConfig(method=method))
        assert idx.shape == (0, 2) and dist.shape == (0,)


def _features(desc, device):
    n = desc.shape[0]
    return FrameFeatures(torch.zeros(n, 2), desc, torch.zeros(n, 3), torch.ones(n, dtype=torch.bool),
                         torch.ones(n), torch.eye(3, dtype=torch.float64), (48, 64)).to(device)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs CUDA"))])
def test_match_features_all_keypoints_on_device(device):
    """The matches' indices live on the features' device (no hard-coded device)."""
    g = torch.Generator().manual_seed(1)
    desc = torch.randint(0, 256, (8, 32), generator=g, dtype=torch.uint8)
    fa, fb = _features(desc, device), _features(desc[[3, 1, 7, 0]].clone(), device)
    idx, dist = match_features(fa, fb, MatchConfig(method="mnn"))
    assert idx.device.type == device
    assert sorted(idx.tolist()) == [[0, 3], [1, 1], [3, 0], [7, 2]]
    assert dist.tolist() == [0.0] * 4
