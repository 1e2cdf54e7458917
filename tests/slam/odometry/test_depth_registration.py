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


# ---------------------------------------------------------------------------------------------------------
# The warp against its first implementation (a scatter, slower): the grid-then-2x2-minimum z-buffer and
# the numpy path must give the same bits as the four-way scatter it replaced.

def _reference_warp(depth, K_depth, K_rgb, T_rgb_depth, rgb_size, min_depth=0.0):
    """The first implementation of register_depth_to_color (a 2x2 splat scattered four ways, in torch)."""
    from slam.lie import quat_to_rotmat

    h, w = int(rgb_size[0]), int(rgb_size[1])
    dtype = depth.dtype if depth.is_floating_point() else torch.float32
    d = torch.nan_to_num(depth.to(dtype), nan=0.0)
    H, W = d.shape
    Kd, Kc, T = K_depth.to(dtype), K_rgb.to(dtype), T_rgb_depth.to(dtype)
    R = quat_to_rotmat(T[3:])
    u = ((torch.arange(W, dtype=dtype) - Kd[0, 2]) / Kd[0, 0])[None, :]
    v = ((torch.arange(H, dtype=dtype) - Kd[1, 2]) / Kd[1, 1])[:, None]
    qx = (R[0, 0] * u + R[0, 1] * v + R[0, 2]) * d + T[0]
    qy = (R[1, 0] * u + R[1, 1] * v + R[1, 2]) * d + T[1]
    zc = (R[2, 0] * u + R[2, 1] * v + R[2, 2]) * d + T[2]
    ok = (d > min_depth) & (zc > min_depth)
    inv_z = 1.0 / torch.where(ok, zc, torch.ones_like(zc))
    x0 = torch.floor(qx * inv_z * Kc[0, 0] + Kc[0, 2])
    y0 = torch.floor(qy * inv_z * Kc[1, 1] + Kc[1, 2])
    ok = (ok & (x0 >= -1) & (x0 < w) & (y0 >= -1) & (y0 < h)).reshape(-1)
    x0 = torch.where(ok, x0.reshape(-1), 0).long()
    y0 = torch.where(ok, y0.reshape(-1), 0).long()
    dummy = h * w
    base = y0 * w + x0
    left, right = ok & (x0 >= 0), ok & (x0 + 1 < w)
    top, bottom = y0 >= 0, y0 + 1 < h
    idx = torch.cat([torch.where(left & top, base, dummy), torch.where(right & top, base + 1, dummy),
                     torch.where(left & bottom, base + w, dummy), torch.where(right & bottom, base + w + 1, dummy)])
    big = torch.finfo(dtype).max
    zbuf = torch.full((h * w + 1,), big, dtype=dtype)
    zbuf.scatter_reduce_(0, idx, zc.reshape(-1).repeat(4), reduce="amin")
    zbuf = zbuf[:dummy]
    return torch.where(zbuf < big, zbuf, torch.zeros_like(zbuf)).reshape(h, w)


def _torch_path(*args, **kwargs):
    """The torch warp (what a non-CPU device runs), called on the CPU."""
    import slam.odometry.depth_registration as dr

    depth, K_depth, K_rgb, T, size = args
    md = kwargs.get("min_depth", 0.0)
    dtype = depth.dtype if depth.is_floating_point() else torch.float32
    if size[0] <= 0 or size[1] <= 0:
        return torch.zeros(max(size[0], 0), max(size[1], 0), dtype=dtype)
    Tt = T.to(dtype)
    return dr._warp_torch(torch.nan_to_num(depth.to(dtype), nan=0.0), K_depth.to(dtype), K_rgb.to(dtype),
                          dr.quat_to_rotmat(Tt[3:]), Tt[:3], int(size[0]), int(size[1]), md)


def test_warp_bitwise_equal_to_the_reference_on_the_kitchen(redkitchen_dir):
    from slam.io import open_sequence

    seq = open_sequence(redkitchen_dir)
    Kd = torch.from_numpy(seq.K)
    Kc = torch.tensor([[525.0, 0, 320], [0, 525.0, 240], [0, 0, 1]], dtype=torch.float64)
    for i in (0, 333, 666, 999):
        depth = torch.from_numpy(seq[i].depth)
        for T in (_pose(-0.025), torch.cat([torch.tensor([0.01, -0.02, 0.03], dtype=torch.float64),
                                            so3_exp(torch.tensor([0.02, -0.01, 0.03], dtype=torch.float64))])):
            ref = _reference_warp(depth, Kd, Kc, T, (480, 640))
            assert ref.count_nonzero() > 100_000  # a real depth map, most of it warped
            assert torch.equal(register_depth_to_color(depth, Kd, Kc, T, (480, 640)), ref)
            assert torch.equal(_torch_path(depth, Kd, Kc, T, (480, 640)), ref)


@pytest.mark.parametrize("seed", range(12))
def test_warp_bitwise_equal_to_the_reference_on_generated_input(seed):
    g = torch.Generator().manual_seed(seed)
    H, W = int(torch.randint(1, 40, (1,), generator=g)), int(torch.randint(1, 50, (1,), generator=g))
    dtype = torch.float64 if seed % 3 == 0 else torch.float32
    depth = torch.rand(H, W, generator=g, dtype=dtype) * 4
    depth[torch.rand(H, W, generator=g) < 0.2] = 0.0
    depth[torch.rand(H, W, generator=g) < 0.05] = float("nan")
    if seed % 4 == 0:
        depth[0, 0] = float("inf")  # becomes the largest float, as torch.nan_to_num makes it
    rot = torch.randn(3, generator=g, dtype=torch.float64) * (0.1 if seed % 2 else 0.0)
    T = torch.cat([torch.randn(3, generator=g, dtype=torch.float64) * 0.05, so3_exp(rot)])
    K1 = torch.tensor([[50.0, 0, W / 2], [0, 55.0, H / 2], [0, 0, 1]], dtype=torch.float64)
    K2 = torch.tensor([[45.0, 0, W / 2 - 1], [0, 47.0, H / 2 + 0.5], [0, 0, 1]], dtype=torch.float64)
    size = (max(0, H + int(torch.randint(-3, 4, (1,), generator=g))), W + 2 - (seed == 5) * (W + 2))
    md = 0.5 if seed % 2 else 0.0
    before = depth.clone()
    ref = _reference_warp(depth, K1, K2, T, size, min_depth=md)
    out = register_depth_to_color(depth, K1, K2, T, size, min_depth=md)
    assert out.dtype == ref.dtype and out.shape == ref.shape and torch.equal(out, ref)
    assert torch.equal(_torch_path(depth, K1, K2, T, size, min_depth=md), ref)
    assert torch.equal(depth.isnan(), before.isnan()) and torch.equal(depth.nan_to_num(), before.nan_to_num())


def test_warp_of_integer_depth_and_edge_sizes():
    depth = torch.full((6, 8), 2, dtype=torch.int32)
    out = register_depth_to_color(depth, K, K, _pose(0.01), (6, 8))
    assert out.dtype == torch.float32 and torch.equal(out, _reference_warp(depth, K, K, _pose(0.01), (6, 8)))
    assert register_depth_to_color(torch.zeros(0, 0), K, K, _pose(), (0, 5)).shape == (0, 5)
    one = register_depth_to_color(torch.full((1, 1), 2.0), K, K, _pose(), (1, 1))
    assert one.shape == (1, 1) and torch.equal(one, _reference_warp(torch.full((1, 1), 2.0), K, K, _pose(), (1, 1)))
