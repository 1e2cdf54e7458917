"""Depth-to-colour registration: hand-computed parallax, z-buffer, invalid pixels, shape errors."""
import pytest
import torch

from slam.lie import se3_log, so3_exp
from slam.odometry.depth_registration import depth_camera_poses, register_depth_to_color

K = torch.tensor([[500.0, 0.0, 32.0], [0.0, 500.0, 24.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _pose(tx=0.0, ty=0.0, tz=0.0):
    return torch.tensor([tx, ty, tz, 0.0, 0.0, 0.0, 1.0], dtype=torch.float64)


def test_identity_rig_returns_the_depth():
    depth = 1.0 + torch.rand(48, 64, generator=torch.Generator().manual_seed(0))
    out = register_depth_to_color(depth, K, K, _pose(), (48, 64))
    # each pixel lands on itself; the 2x2 splat may also put a nearer right/lower neighbour's depth on it
    assert out.shape == (48, 64) and out.dtype == depth.dtype
    assert (out <= depth + 1e-6).all()
    assert torch.equal(out[0, 0], depth[0, 0])


def test_parallax_of_a_sideways_baseline():
    depth = torch.zeros(48, 64)
    depth[24, 20] = 2.0  # one point at x = (20 - 32) / 500 * 2 m
    out = register_depth_to_color(depth, K, K, _pose(tx=0.1), (48, 64))
    # p_rgb = p_depth + (0.1, 0, 0): the pixel moves by f * t / z = 500 * 0.1 / 2 = 25 px
    hit = torch.nonzero(out)
    assert hit[:, 1].min().item() == 45 and hit[:, 0].min().item() == 24
    assert torch.allclose(out[out > 0], torch.tensor(2.0))


def test_nearest_surface_wins_and_depth_along_the_colour_axis():
    depth = torch.zeros(48, 64)
    depth[10, 10] = 1.0
    depth[10, 35] = 2.0  # with tx = 0.05: 1 m moves 25 px to x=35, 2 m moves 12.5 px to x=47.5
    out = register_depth_to_color(depth, K, K, _pose(tx=0.05, tz=0.5), (48, 64))
    # tz = 0.5: the colour camera sees both 0.5 m farther
    assert torch.allclose(out[out > 0].unique(), torch.tensor([1.5, 2.5]))
    occl = torch.zeros(48, 64)
    occl[10, 10] = 1.0
    occl[10, 35] = 2.0
    occl[10, 22] = 1.0  # lands at x = 22 + 25 = 47, on top of the 2 m point's splat
    out = register_depth_to_color(occl, K, K, _pose(tx=0.05), (48, 64))
    assert out[10, 47].item() == pytest.approx(1.0)


def test_invalid_depth_and_empty_input():
    depth = torch.full((48, 64), float("nan"))
    depth[0, 0] = 0.0
    out = register_depth_to_color(depth, K, K, _pose(0.02), (30, 40))
    assert out.shape == (30, 40) and not out.any()


def test_shape_errors_name_the_argument():
    with pytest.raises(ValueError, match="depth must have shape"):
        register_depth_to_color(torch.zeros(2, 3, 4), K, K, _pose(), (3, 4))
    with pytest.raises(ValueError, match="K_rgb"):
        register_depth_to_color(torch.zeros(3, 4), K, torch.eye(4), _pose(), (3, 4))
    with pytest.raises(ValueError, match="T_rgb_depth"):
        register_depth_to_color(torch.zeros(3, 4), K, K, torch.zeros(6), (3, 4))


def test_depth_camera_poses_hand_case():
    # the colour camera turns 90 deg about its y axis in place; the depth camera, 2.5 cm to its left
    # (x = -0.025), swings on a circle around it
    T = _pose(tx=-0.025)
    q = so3_exp(torch.tensor([0.0, torch.pi / 2, 0.0], dtype=torch.float64))
    P_rgb = torch.stack([_pose(), torch.cat([torch.zeros(3, dtype=torch.float64), q])])
    P = depth_camera_poses(P_rgb, T)
    assert torch.allclose(P[0], _pose(), atol=1e-12)
    # R_y(90 deg) maps (x, 0, 0) to (0, 0, -x): R t = (0, 0, 0.025), so the depth camera moved R t - t
    assert torch.allclose(P[1, :3], torch.tensor([0.025, 0.0, 0.025], dtype=torch.float64), atol=1e-12)
    assert torch.allclose(se3_log(P[1])[3:], torch.tensor([0.0, torch.pi / 2, 0.0], dtype=torch.float64), atol=1e-12)
    with pytest.raises(ValueError, match="T_rgb_depth"):
        depth_camera_poses(P_rgb, torch.zeros(3))
