"""The keyframe point-cloud map: voxel downsampling, back-projection (registered and through a rig),
placement with poses, the PLY file (against plyfile as an independent reader), and points on the
synthetic scene's known surfaces."""
from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from slam.lie import quat_to_rotmat, se3_exp
from slam.mapping import (
    MapConfig,
    PLYFormatError,
    PointCloudMap,
    keyframe_cloud,
    read_ply,
    voxel_downsample,
    write_ply,
)


def _K(f=100.0, w=64, h=48):
    return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])


def test_voxel_downsample_hand_computed():
    p = np.array([[0.01, 0.01, 0.01], [0.09, 0.02, 0.03], [0.11, 0.0, 0.0], [-0.01, 0.0, 0.0]])
    c = np.array([[10, 20, 30], [30, 40, 50], [1, 2, 3], [200, 200, 200]], np.uint8)
    q, d = voxel_downsample(p, c, 0.1)
    order = np.lexsort(q.T[::-1])
    q, d = q[order], d[order]
    assert q.shape == (3, 3) and d.dtype == np.uint8
    np.testing.assert_allclose(q, [[-0.01, 0, 0], [0.05, 0.015, 0.02], [0.11, 0, 0]], atol=1e-7)
    assert d.tolist() == [[200, 200, 200], [20, 30, 40], [1, 2, 3]]


def test_voxel_downsample_empty_and_bad_shapes():
    q, d = voxel_downsample(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), 0.05)
    assert q.shape == (0, 3) and d.shape == (0, 3)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        voxel_downsample(np.zeros((4, 2)), np.zeros((4, 2), np.uint8), 0.05)
    with pytest.raises(ValueError, match="voxel_size"):
        voxel_downsample(np.zeros((1, 3)), np.zeros((1, 3), np.uint8), float("inf"))


def test_voxel_downsample_far_from_origin_keeps_voxels_apart():
    """Large coordinates (a 100 km offset): cells are relative to the minimum, no int64 overflow."""
    rng = np.random.default_rng(0)
    p = rng.uniform(0, 1, (500, 3)) + 1e5
    q, _ = voxel_downsample(p, np.zeros_like(p, dtype=np.uint8), 0.25)
    assert 32 <= q.shape[0] <= 64  # 4^3 cells, each occupied by ~8 points


def test_keyframe_cloud_of_a_wall_lies_on_it():
    """A fronto-parallel wall 2 m ahead: every point at z = 2, spread over the frustum, colours kept."""
    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[..., 0] = 255
    pts, cols = keyframe_cloud(rgb, np.full((48, 64), 2.0, np.float32), _K(), MapConfig(voxel_size=0.04))
    np.testing.assert_allclose(pts[:, 2], 2.0, atol=1e-6)
    half_w = (63 / 2) / 100 * 2  # the frustum's half width at 2 m
    assert pts[:, 0].min() >= -half_w - 1e-6 and pts[:, 0].max() <= half_w + 1e-6
    assert pts[:, 0].max() - pts[:, 0].min() > 1.8 * half_w - 0.04
    assert (cols == [255, 0, 0]).all()


def test_keyframe_cloud_depth_range_and_invalid_pixels():
    depth = np.full((48, 64), 2.0, np.float32)
    depth[:, :32] = 0.0  # invalid
    depth[:24, 32:] = 9.0  # beyond the range
    pts, _ = keyframe_cloud(np.zeros((48, 64, 3), np.uint8), depth, _K(), MapConfig(voxel_size=0.01),
                            depth_range=(0.3, 4.0))
    assert pts.shape[0] > 0
    np.testing.assert_allclose(pts[:, 2], 2.0, atol=1e-6)
    assert (pts[:, 0] > -0.01).all()  # only the right half


def test_unregistered_rig_colour_from_colour_camera_geometry_from_depth_camera():
    """A wall 2 m ahead seen by a depth camera 0.1 m to the colour camera's left (t = (-0.1, 0, 0)).

    The colour image is red left of the colour camera's optical axis and blue right of it. In the depth
    camera's frame the colour boundary is where the colour camera's axis meets the wall: x = +0.1 m; the
    geometry (z = 2) is the depth camera's.
    """
    w, h, f = 64, 48, 100.0
    K = _K(f, w, h)
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[:, : w // 2] = (255, 0, 0)
    rgb[:, w // 2:] = (0, 0, 255)
    t = (-0.1, 0.0, 0.0)
    pts, cols = keyframe_cloud(rgb, np.full((h, w), 2.0, np.float32), K, MapConfig(voxel_size=0.01),
                               rgb_intrinsics=(f, f, (w - 1) / 2, (h - 1) / 2), rgb_from_depth=t)
    np.testing.assert_allclose(pts[:, 2], 2.0, atol=1e-5)
    red = (cols == [255, 0, 0]).all(1)
    blue = (cols == [0, 0, 255]).all(1)
    assert red.sum() > 100 and blue.sum() > 100
    assert pts[red, 0].max() < 0.1 + 0.02 and pts[blue, 0].min() > 0.1 - 0.03
    # registered reading of the same images would put the boundary at x = 0 instead
    pts0, cols0 = keyframe_cloud(rgb, np.full((h, w), 2.0, np.float32), K, MapConfig(voxel_size=0.01))
    assert abs(pts0[(cols0 == [255, 0, 0]).all(1), 0].max()) < 0.02


def test_map_places_each_keyframe_with_its_pose():
    m = PointCloudMap(MapConfig(voxel_size=0.05))
    rgb = np.full((48, 64, 3), 128, np.uint8)
    m.add(0, rgb, np.full((48, 64), 2.0, np.float32), _K())
    m.add(1, rgb, np.full((48, 64), 1.0, np.float32), _K())
    local0 = keyframe_cloud(rgb, np.full((48, 64), 2.0, np.float32), _K(), m.config)[0]
    pose = se3_exp(torch.tensor([[0.3, -0.2, 5.0, 0.1, 0.4, -0.2]], dtype=torch.float64))[0]
    poses = torch.stack([pose, torch.tensor([0.0, 0, 0, 0, 0, 0, 1], dtype=torch.float64)])
    pts, cols = m.points(poses)
    R, t = quat_to_rotmat(pose[3:]).numpy(), pose[:3].numpy()
    expected = local0 @ R.T + t
    # keyframe 0's points land near its transformed cloud (the merge re-voxelises: within a voxel diagonal)
    near = pts[np.linalg.norm(pts, axis=1) > 2.0]  # keyframe 1's points are within 1.2 m of the origin, 0's beyond 3 m
    d = np.linalg.norm(near[:, None] - expected[None], axis=-1).min(1)
    assert near.shape[0] > 100 and d.max() < 0.05 * np.sqrt(3)
    assert m.num_points == local0.shape[0] + m._clouds[1][0].shape[0]
    assert cols.shape == pts.shape and cols.dtype == np.uint8
    # a keyframe without a pose (beyond M, or non-finite) is left out
    only0 = m.points(poses[:1])[0]
    assert only0.shape[0] < pts.shape[0]
    bad = poses.clone()
    bad[1, 0] = float("nan")
    assert m.points(bad)[0].shape[0] == only0.shape[0]


def test_a_dropped_keyframe_leaves_the_map():
    m = PointCloudMap(MapConfig(voxel_size=0.05))
    rgb = np.full((48, 64, 3), 128, np.uint8)
    m.add(0, rgb, np.full((48, 64), 2.0, np.float32), _K())
    m.add(1, rgb, np.full((48, 64), 1.0, np.float32), _K())
    n0 = keyframe_cloud(rgb, np.full((48, 64), 2.0, np.float32), _K(), m.config)[0].shape[0]
    poses = torch.tensor([[0.0, 0, 0, 0, 0, 0, 1]] * 2, dtype=torch.float64)
    m.drop([1, 7])  # 7 has no points: skipped
    pts, _ = m.points(poses)
    assert len(m) == 1 and m.num_points == n0 and m.nbytes == 9 * n0 + 8
    assert np.allclose(pts[:, 2], 2.0, atol=0.05)  # keyframe 0's wall 2 m ahead alone; 1's at 1 m is gone


def test_ply_round_trip_and_layout():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(257, 3)).astype(np.float32)
    cols = rng.integers(0, 256, (257, 3), dtype=np.uint8)
    buf = io.BytesIO()
    write_ply(buf, pts, cols, comment="test cloud")
    data = buf.getvalue()
    header = data[: data.index(b"end_header\n") + len(b"end_header\n")].decode()
    assert header.startswith("ply\nformat binary_little_endian 1.0\n")
    assert "element vertex 257\n" in header and "property uchar red\n" in header
    assert len(data) == len(header) + 257 * 15  # 3 float32 + 3 uchar per vertex, nothing else
    p2, c2 = read_ply(io.BytesIO(data))
    np.testing.assert_array_equal(p2, pts.astype(np.float64))
    np.testing.assert_array_equal(c2, cols)


def test_ply_read_by_plyfile(tmp_path):
    """An independent reader (plyfile) reads what write_ply writes."""
    plyfile = pytest.importorskip("plyfile", reason="plyfile (attnloop[dev]) is the independent PLY reader")
    pts = np.array([[0.5, -1.0, 2.0], [1e3, 0.0, -3.25]], np.float32)
    cols = np.array([[1, 2, 3], [255, 128, 0]], np.uint8)
    write_ply(tmp_path / "m.ply", pts, cols)
    v = plyfile.PlyData.read(str(tmp_path / "m.ply"))["vertex"]
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), pts)
    np.testing.assert_array_equal(np.stack([v["red"], v["green"], v["blue"]], 1), cols)


def test_ply_errors_name_the_file(tmp_path):
    with pytest.raises(ValueError, match="non-finite"):
        write_ply(io.BytesIO(), np.array([[np.inf, 0, 0]]), np.zeros((1, 3), np.uint8))
    (tmp_path / "x.ply").write_bytes(b"not a ply")
    with pytest.raises(PLYFormatError, match="x.ply"):
        read_ply(tmp_path / "x.ply")
    buf = io.BytesIO()
    write_ply(buf, np.zeros((10, 3), np.float32), np.zeros((10, 3), np.uint8))
    (tmp_path / "cut.ply").write_bytes(buf.getvalue()[:-7])
    with pytest.raises(PLYFormatError, match="cut.ply.*10 vertices"):
        read_ply(tmp_path / "cut.ply")


def test_map_of_exact_frames_lies_on_the_scene_surfaces():
    """Noise-free synthetic frames with their true poses: every map point within a voxel of a surface."""
    from slam.synthetic import SyntheticSequence
    from slam.synthetic.sequence import _tiny_scene

    scene = _tiny_scene()
    seq = SyntheticSequence("loop", num_frames=40, width=160, height=120, depth_noise=False, image_noise=False,
                            scene=scene)
    m = PointCloudMap(MapConfig(voxel_size=0.02))
    ids = list(range(0, 40, 8))
    for k, i in enumerate(ids):
        f = seq[i]
        assert m.add(k, f.rgb, f.depth, f.K) > 500
    poses = torch.from_numpy(np.stack([seq[i].pose_gt for i in ids]))
    pts, cols = m.points(poses)
    assert pts.shape[0] > 5000
    dist = scene.surface_distance(torch.from_numpy(pts.astype(np.float32))).abs().numpy()
    # a voxel's centroid is off the surface only where the voxel holds a corner or an edge
    assert np.median(dist) < 2e-3, np.median(dist)
    assert np.quantile(dist, 0.99) < 0.02 * np.sqrt(3) / 2, np.quantile(dist, 0.99)
    assert cols.std() > 10  # photo textures, not a flat colour


def test_kept_points_are_int16_steps_within_half_a_step_of_the_cloud():
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    depth = rng.uniform(1.0, 3.5, (48, 64)).astype(np.float32)
    cfg = MapConfig(voxel_size=0.02)
    m = PointCloudMap(cfg)
    n = m.add(0, rgb, depth, _K())
    ref_pts, ref_cols = keyframe_cloud(rgb, depth, _K(), cfg)
    pts, cols = m.local_points(0)
    q, step, _ = m._clouds[0]
    assert q.dtype == np.int16 and step == cfg.voxel_size / 16  # 1.25 mm: reach 3.5 m needs only 0.11 mm
    assert n == ref_pts.shape[0] and (cols == ref_cols).all()
    assert np.abs(pts - ref_pts).max() <= step / 2 + 1e-6  # float32 coordinates of metres
    assert m.nbytes == n * 9 + 8  # 6 bytes of coordinates and 3 of colour a point, the step


def test_a_far_cloud_takes_a_coarser_step_within_int16():
    cfg = MapConfig(voxel_size=0.02, max_depth=200.0)
    m = PointCloudMap(cfg)
    m.add(0, np.full((48, 64, 3), 9, np.uint8), np.full((48, 64), 150.0, np.float32), _K())
    q, step, _ = m._clouds[0]
    pts = m.local_points(0)[0]
    ref = keyframe_cloud(np.full((48, 64, 3), 9, np.uint8), np.full((48, 64), 150.0, np.float32), _K(), cfg)[0]
    assert step == pytest.approx(150.0 / 32000) and np.abs(q).max() <= 32000
    assert np.abs(pts - ref).max() <= step / 2 + 1e-5


def test_a_keyframe_keeps_only_what_the_keyframes_before_it_do_not_hold():
    """A wall 2 m ahead seen from three camera positions 0.5 m apart along it: the second and third views
    keep only the strip the earlier ones did not see; the merged map equals the one that keeps every point
    to a voxel."""
    K = _K(f=50.0)
    rgb = np.full((48, 64, 3), 120, np.uint8)
    depth = np.full((48, 64), 2.0, np.float32)  # the view spans 2 * 2.0 * 32 / 50 = 2.56 m of the wall
    step = torch.tensor([0.5, 0, 0, 0, 0, 0, 1], dtype=torch.float64)  # 0.5 m to the right, same orientation
    poses = torch.tensor([[0.5 * k, 0, 0, 0, 0, 0, 1] for k in range(3)], dtype=torch.float64)
    full = PointCloudMap(MapConfig(voxel_size=0.05, overlap_keyframes=0))
    compact = PointCloudMap(MapConfig(voxel_size=0.05))
    for k in range(3):
        ref = None if k == 0 else (k - 1, step if k == 1 else step.numpy())  # the pose as a tensor or an array
        all_pts = full.add(k, rgb, depth, K, reference=ref)
        kept = compact.add(k, rgb, depth, K, reference=ref)
        if k == 0:
            assert kept == all_pts
        else:  # the new 0.5 m strip of a 2.56 m view: about a fifth of its voxels
            assert 0.15 < kept / all_pts < 0.25, (kept, all_pts)
            assert compact.local_points(k)[0][:, 0].min() > 1.28 - 0.5 - 0.05 - 1e-6  # the right edge only
    a, b = full.points(poses)[0], compact.points(poses)[0]
    d = np.linalg.norm(a[:, None] - b[None], axis=-1).min(1)
    assert b.shape[0] < a.shape[0] * 1.01 and d.max() < 0.05 * np.sqrt(3)
    # a keyframe without a reference among the recent ones starts a new chain: it keeps everything
    assert compact.add(7, rgb, depth, K, reference=(5, step)) == all_pts


def test_overlap_keyframes_must_be_a_count():
    with pytest.raises(ValueError, match="MapConfig.overlap_keyframes must be an integer >= 0, got -1"):
        MapConfig(overlap_keyframes=-1)
