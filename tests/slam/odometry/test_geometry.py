"""Back-projection, Kabsch, covariances and information matrices of slam.odometry.geometry."""
import math

import pytest
import torch

from slam.lie import quat_to_rotmat, se3_act, se3_between, se3_compose, se3_exp, se3_log
from slam.odometry.geometry import (
    backproject,
    depth_sigma,
    kabsch,
    point_covariance,
    project,
    rigid_jacobian,
    transform_points,
)
from slam.odometry.ransac import refine_rigid

K = torch.tensor([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _random_pose(seed: int, scale: float = 0.5) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return se3_exp(scale * torch.randn(6, generator=g, dtype=torch.float64))


def test_backproject_matches_hand_computation():
    depth = torch.full((480, 640), 2.0, dtype=torch.float64)
    depth[51, 100] = 2.5  # the rounded pixel of the first keypoint
    depth[50:53, 99:102] = 2.5  # a smooth 3x3 neighbourhood around it
    kp = torch.tensor([[100.4, 50.6], [320.0, 240.0]], dtype=torch.float64)
    pts, ok = backproject(kp, depth, K)
    assert ok.tolist() == [True, True]
    # by hand: X = (x - cx) / fx * z with the *unrounded* x, z read at the rounded pixel (100, 51)
    expected = torch.tensor([[(100.4 - 320.0) / 585.0 * 2.5, (50.6 - 240.0) / 585.0 * 2.5, 2.5],
                             [0.0, 0.0, 2.0]], dtype=torch.float64)
    assert torch.allclose(pts, expected, atol=1e-12)
    # re-projecting gives the keypoints back
    assert torch.allclose(project(pts, K), kp, atol=1e-9)


def test_backproject_rejects_invalid_range_discontinuity_and_border():
    depth = torch.full((100, 120), 1.5)
    depth[10, 10] = 0.0  # invalid pixel
    depth[30, 30] = 9.0  # beyond max_depth
    depth[51, 60] = 1.0  # a 0.5 m jump next to (60, 50)
    kp = torch.tensor([[10.0, 10.0], [30.0, 30.0], [60.0, 50.0], [0.0, 50.0], [80.0, 80.0], [500.0, 5.0]])
    _, ok = backproject(kp, depth, K.float(), min_depth=0.3, max_depth=4.0)
    assert ok.tolist() == [False, False, False, False, True, False]
    # without the window check the discontinuity and the border pixel are accepted
    _, ok0 = backproject(kp, depth, K.float(), window_radius=0)
    assert ok0.tolist() == [False, False, True, True, True, False]


def test_backproject_empty_and_bad_shapes():
    pts, ok = backproject(torch.zeros(0, 2), torch.ones(4, 4), K)
    assert pts.shape == (0, 3) and ok.shape == (0,)
    with pytest.raises(ValueError, match="keypoints"):
        backproject(torch.zeros(3, 3), torch.ones(4, 4), K)
    with pytest.raises(ValueError, match="depth"):
        backproject(torch.zeros(3, 2), torch.ones(4, 4, 1), K)


def test_kabsch_recovers_known_transform_batched_and_weighted():
    g = torch.Generator().manual_seed(1)
    poses = torch.stack([_random_pose(s) for s in range(4)])  # (4, 7)
    src = torch.randn(4, 20, 3, generator=g, dtype=torch.float64)
    dst = transform_points(poses, src)
    est = kabsch(src, dst)
    assert se3_log(se3_between(poses, est)).abs().max() < 1e-10
    # a corrupted point with weight 0 changes nothing
    dst_bad = dst.clone()
    dst_bad[:, 0] += 5.0
    w = torch.ones(4, 20, dtype=torch.float64)
    w[:, 0] = 0.0
    est_w = kabsch(src, dst_bad, w)
    assert se3_log(se3_between(poses, est_w)).abs().max() < 1e-10
    assert se3_log(se3_between(poses, kabsch(src, dst_bad))).abs().max() > 1e-3


def test_kabsch_never_returns_a_reflection():
    g = torch.Generator().manual_seed(2)
    src = torch.randn(30, 3, generator=g, dtype=torch.float64)
    mirrored = src * torch.tensor([1.0, -1.0, 1.0], dtype=torch.float64)
    R = quat_to_rotmat(kabsch(src, mirrored)[3:])
    assert torch.allclose(torch.linalg.det(R), torch.tensor(1.0, dtype=torch.float64))
    assert torch.allclose(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-12)


def test_kabsch_shape_errors():
    with pytest.raises(ValueError, match="src and dst"):
        kabsch(torch.zeros(5, 3), torch.zeros(4, 3))
    with pytest.raises(ValueError, match="weights"):
        kabsch(torch.zeros(5, 3), torch.zeros(5, 3), torch.ones(4))


def test_rigid_jacobian_is_the_derivative_of_the_right_perturbation():
    g = torch.Generator().manual_seed(3)
    p = torch.randn(5, 3, generator=g, dtype=torch.float64)
    J = rigid_jacobian(p)
    eps = 1e-6
    for k in range(6):
        d = torch.zeros(6, dtype=torch.float64)
        d[k] = eps
        num = (se3_act(se3_exp(d)[None], p) - se3_act(se3_exp(-d)[None], p)) / (2 * eps)
        assert torch.allclose(J[:, :, k], num, atol=1e-8)


def test_information_is_symmetric_pd_and_equals_the_gauss_newton_hessian():
    g = torch.Generator().manual_seed(4)
    src = torch.randn(40, 3, generator=g, dtype=torch.float64) + torch.tensor([0.0, 0.0, 2.0],
                                                                              dtype=torch.float64)
    sigma = 0.01 + 0.01 * torch.rand(40, generator=g, dtype=torch.float64)
    T = _random_pose(5)
    dst = transform_points(T, src)
    # the refinement's information, given isotropic covariances that add up to sigma^2 per residual
    cov = (sigma ** 2 / 2)[:, None, None] * torch.eye(3, dtype=torch.float64)
    _, H = refine_rigid(T, src, dst, cov, cov, iterations=0)
    assert torch.allclose(H, H.T)
    assert torch.linalg.eigvalsh(H).min() > 0

    # independent reference: half the finite-difference Hessian of the cost at the (zero-residual) optimum
    def cost(xi):
        r = transform_points(se3_compose(T, se3_exp(xi)), src) - dst
        return 0.5 * ((r ** 2).sum(-1) / sigma ** 2).sum()

    Hnum = torch.autograd.functional.hessian(cost, torch.zeros(6, dtype=torch.float64))
    assert torch.allclose(H, Hnum, rtol=1e-6, atol=1e-6)


def test_refinement_reaches_the_weighted_least_squares_optimum():
    # with isotropic, equal covariances the Mahalanobis optimum is the plain Kabsch fit
    g = torch.Generator().manual_seed(6)
    src = torch.randn(50, 3, generator=g, dtype=torch.float64)
    T = _random_pose(7)
    dst = transform_points(T, src) + 0.01 * torch.randn(50, 3, generator=g, dtype=torch.float64)
    cov = 1e-4 * torch.eye(3, dtype=torch.float64).expand(50, 3, 3)
    start = se3_compose(kabsch(src, dst), se3_exp(torch.full((6,), 0.01, dtype=torch.float64)))
    refined, _ = refine_rigid(start, src, dst, cov, cov, iterations=10, huber_delta=1e9)
    assert se3_log(se3_between(kabsch(src, dst), refined)).abs().max() < 1e-8


def test_point_covariance_matches_numerical_propagation():
    u, v, z = 400.0, 100.0, 2.0
    sz, spx = 0.01, 1.5

    def bp(x):  # (u, v, z) -> point
        return torch.stack([(x[0] - K[0, 2]) / K[0, 0] * x[2], (x[1] - K[1, 2]) / K[1, 1] * x[2], x[2]])

    x0 = torch.tensor([u, v, z], dtype=torch.float64)
    J = torch.autograd.functional.jacobian(bp, x0)
    ref = J @ torch.diag(torch.tensor([spx ** 2, spx ** 2, sz ** 2], dtype=torch.float64)) @ J.T
    cov = point_covariance(bp(x0)[None], torch.tensor([sz], dtype=torch.float64),
                           torch.tensor([spx], dtype=torch.float64), 585.0, 585.0)[0]
    # first-order propagation is exact here: the back-projection is linear in (u, v) for fixed z
    assert torch.allclose(cov, ref, rtol=1e-9, atol=1e-15)


def test_depth_sigma_kinect_model():
    z = torch.tensor([0.4, 1.0, 3.0], dtype=torch.float64)
    expected = 0.0012 + 0.0019 * (z - 0.4) ** 2
    assert torch.allclose(depth_sigma(z), expected)
    assert math.isclose(float(depth_sigma(torch.tensor(0.4))), 0.0012, rel_tol=1e-6)


def test_transform_points_rotates_by_the_pose_quaternion():
    """transform_points(pose, p) = R(q) p + t, with R from slam.lie, against a hand-built rotation (90 degrees
    about z) and on seeded poses."""
    from slam.odometry.geometry import transform_points

    s = math.sqrt(0.5)
    pose = torch.tensor([1.0, 2.0, 3.0, 0.0, 0.0, s, s], dtype=torch.float64)  # 90 deg about z, then t
    pts = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    assert torch.allclose(transform_points(pose, pts), torch.tensor([[1.0, 3.0, 3.0], [0.0, 2.0, 3.0]],
                                                                    dtype=torch.float64), atol=1e-15)
    g = torch.Generator().manual_seed(0)
    q = torch.randn(4, generator=g, dtype=torch.float64)
    pose = torch.cat([torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64), q / q.norm()])
    pts = torch.randn(20, 3, generator=g, dtype=torch.float64)
    assert torch.equal(transform_points(pose, pts), pts @ quat_to_rotmat(pose[3:]).T + pose[:3])
