"""The synthetic RGB-D generator: exact geometry, consistent views, TUM layout, determinism, noise."""
from __future__ import annotations

import logging
import math

import cv2
import numpy as np
import pytest
import torch
from helpers import free_space_distance

from slam.io.trajectory import read_tum_trajectory
from slam.io.tum import read_calibration_file
from slam.lie import se3_act, se3_between, se3_inv, so3_log
from slam.synthetic import scene as scene_mod
from slam.synthetic.render import (
    DepthNoiseConfig,
    ImageNoiseConfig,
    apply_depth_noise,
    apply_image_noise,
    apply_motion_blur,
    render_frames,
)
from slam.synthetic.scene import BoxSpec, RoomConfig, build_room_scene, tensorize
from slam.synthetic.sequence import (
    SyntheticSequence,
    generate_sequence,
    synthetic_intrinsics,
)
from slam.synthetic.trajectories import TRAJECTORIES, make_trajectory, trajectory_rates

W, H = 160, 120


pytestmark = pytest.mark.usefixtures("one_thread")  # conftest.py


@pytest.fixture(scope="module")
def scene():
    # Coarser textures than the default (faster to build); the geometry is the default room's.
    return build_room_scene(RoomConfig(texel_density=96.0, object_texel_density=128.0))


@pytest.fixture(scope="module")
def K():
    return torch.from_numpy(synthetic_intrinsics(W, H))


def backproject(depth: torch.Tensor, K: torch.Tensor, pose: torch.Tensor):
    """World points (M, 3) float64 and their pixel indices (M,) of the valid depth pixels."""
    h, w = depth.shape
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64),
                          indexing="ij")
    z = depth.double().reshape(-1)
    valid = z > 0
    x = (u.reshape(-1) - K[0, 2]) / K[0, 0] * z
    y = (v.reshape(-1) - K[1, 2]) / K[1, 1] * z
    pts = torch.stack([x, y, z], -1)[valid]
    return se3_act(pose[None].double(), pts), valid.nonzero()[:, 0]


def test_depth_is_z_depth_of_an_empty_room():
    # Independent reference: a camera facing a wall squarely sees the same z-depth in every pixel (the
    # ray length would grow towards the borders).
    tex = np.full((8, 8, 3), 128, np.uint8)
    room = BoxSpec("room", (0.0, 0.0, 0.0), (4.0, 4.0, 4.0), 0.0, [tex] * 6, inside=True)
    sc = tensorize([room], RoomConfig(lights=((0.0, 0.0, 1.5),)))
    K = torch.from_numpy(synthetic_intrinsics(64, 48))
    # camera at the centre looking along +x: camera z = world x, camera x = world -y, camera y = world -z
    R = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    from slam.lie import rotmat_to_quat
    pose = torch.cat([torch.tensor([0.5, 0.2, -0.1], dtype=torch.float64), rotmat_to_quat(R)])
    out = render_frames(sc, K, pose, 48, 64)
    assert torch.allclose(out.depth, torch.full_like(out.depth, 1.5), atol=2e-6)
    assert (out.hit == 1).all()  # room (box 0) face 1 = +x wall
    assert torch.allclose(out.cos_incidence[0, 23:25, 31:33], torch.ones(2, 2), atol=1e-3)


@pytest.mark.parametrize("name", sorted(TRAJECTORIES))
def test_backprojected_depth_lies_on_the_surfaces(scene, K, name):
    traj = make_trajectory(name, 60, seed=1)
    idx = [0, 31, 59]
    out = render_frames(scene, K, traj.poses[idx], H, W)
    for k, i in enumerate(idx):
        assert (out.depth[k] > 0).all()  # a closed room: every ray hits something
        pts, _ = backproject(out.depth[k], K, traj.poses[i])
        dist = scene.surface_distance(pts)
        assert dist.max() < 1e-4, f"frame {i}: a back-projected point is {dist.max():.2e} m off the surfaces"
        # and on the very face the renderer reported: signed distance to that box ~ 0
        box = out.hit[k].reshape(-1) // 6
        sd = scene_mod.box_signed_distance(pts, scene.centers.double(), scene.rotations.double(),
                                           scene.half_sizes.double())
        assert sd.gather(1, box[:, None]).abs().max() < 1e-4


def test_consecutive_frames_reproject_into_each_other(scene, K):
    traj = make_trajectory("loop", 300, seed=0)
    a, b = 120, 121
    out = render_frames(scene, K, traj.poses[[a, b]], H, W)
    pts_w, pix = backproject(out.depth[1], K, traj.poses[b])
    # world -> camera a -> pixels of frame a
    pc = se3_act(se3_inv(traj.poses[a])[None], pts_w)
    u = K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]
    v = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
    ui, vi = u.round().long(), v.round().long()
    inside = (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
    assert inside.float().mean() > 0.8  # most of the view is shared at 30 Hz
    z_a = out.depth[0][vi[inside], ui[inside]].double()
    dz = (pc[inside, 2] - z_a).abs()
    # Nearest-pixel lookup: exact up to the surface slope within half a pixel; occlusions are rare.
    assert torch.median(dz) < 2e-3
    covis = dz < 0.02
    assert covis.float().mean() > 0.95
    # Colours of the same surface points agree (both views see one texture under fixed lights); warping
    # must do far better than comparing the same pixels without motion compensation.
    rgb_a = out.rgb[0].double()
    rgb_b = out.rgb[1].reshape(-1, 3).double()[pix][inside][covis]
    col_a = torch.stack([_bilinear(rgb_a[..., c], u[inside][covis], v[inside][covis]) for c in range(3)], -1)
    warped = (rgb_b - col_a).abs().mean(-1)
    unwarped = (out.rgb[1].double() - out.rgb[0].double()).abs().mean(-1)
    assert torch.median(warped) < 6.0
    assert torch.median(warped) < 0.35 * torch.median(unwarped)


def _bilinear(img: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    h, w = img.shape
    u = u.clamp(0, w - 1.001)
    v = v.clamp(0, h - 1.001)
    u0, v0 = u.floor().long(), v.floor().long()
    fu, fv = u - u0, v - v0
    return ((img[v0, u0] * (1 - fu) + img[v0, u0 + 1] * fu) * (1 - fv)
            + (img[v0 + 1, u0] * (1 - fu) + img[v0 + 1, u0 + 1] * fu) * fv)


def test_tum_layout_and_depth_round_trip(scene, tmp_path):
    folder = generate_sequence(tmp_path / "seq", "loop", num_frames=6, width=W, height=H, seed=5, scene=scene)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "calibration.txt", "synthetic.json"):
        assert (folder / name).is_file()
    rgb_lines = [ln for ln in (folder / "rgb.txt").read_text().splitlines()]
    assert rgb_lines[0].startswith("#") and rgb_lines[2] == "# timestamp filename"
    entries = [ln.split() for ln in rgb_lines if not ln.startswith("#")]
    depth_entries = [ln.split() for ln in (folder / "depth.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(entries) == len(depth_entries) == 6
    assert all(e[1] == f"rgb/{e[0]}.png" for e in entries)
    seq = SyntheticSequence("loop", num_frames=6, width=W, height=H, seed=5, scene=scene)
    gt = read_tum_trajectory(folder / "groundtruth.txt")
    assert torch.allclose(gt.poses, seq.trajectory.poses, atol=2e-9)
    assert np.allclose(gt.timestamps.numpy(), [float(e[0]) for e in entries], atol=0, rtol=0)
    assert np.allclose(read_calibration_file(folder / "calibration.txt").K, synthetic_intrinsics(W, H))
    for (stamp, rgb_name), (_, depth_name), frame in zip(entries, depth_entries, seq):
        raw = cv2.imread(str(folder / depth_name), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16 and raw.shape == (H, W)
        # factor 5000: the file holds round(z * 5000); reading it back gives the in-memory frame exactly
        assert np.array_equal(raw.astype(np.float32) / np.float32(5000.0), frame.depth)
        assert (raw > 0).mean() > 0.8 and 0.4 * 5000 < np.median(raw[raw > 0]) < 5.0 * 5000
        rgb = cv2.imread(str(folder / rgb_name), cv2.IMREAD_COLOR)[:, :, ::-1]
        assert np.array_equal(rgb, frame.rgb)
        assert float(stamp) == pytest.approx(frame.timestamp, abs=1e-9)
    # The TUM reader (if present) sees the same frames.
    tum = pytest.importorskip("slam.io.tum")
    reader = tum.TUMSequence(folder, K=read_calibration_file(folder / "calibration.txt").K)
    assert len(reader) == 6
    f0, s0 = reader[0], seq[0]
    assert np.array_equal(f0.depth, s0.depth) and np.array_equal(f0.rgb, s0.rgb)
    assert np.allclose(f0.pose_gt, s0.pose_gt, atol=2e-9)


def test_noise_free_depth_round_trip_is_sub_millimetre(scene):
    seq = SyntheticSequence("figure_eight", num_frames=5, width=W, height=H, depth_noise=False,
                            image_noise=False, scene=scene)
    frame = seq[2]
    exact = render_frames(scene, torch.from_numpy(seq.K), torch.from_numpy(frame.pose_gt), H, W).depth[0]
    err = (torch.from_numpy(frame.depth) - exact).abs()
    assert err.max() <= 0.5 / 5000 + 1e-6  # the 16-bit quantisation only


def test_deterministic_by_seed_and_independent_of_batching(scene):
    kw = {"num_frames": 5, "width": W, "height": H, "scene": scene}
    a = SyntheticSequence("out_and_back", seed=3, batch_size=3, **kw)
    b = SyntheticSequence("out_and_back", seed=3, batch_size=1, **kw)
    c = SyntheticSequence("out_and_back", seed=4, **kw)
    fa, fb, fc = list(a), list(b), list(c)
    for x, y in zip(fa, fb):
        assert np.array_equal(x.rgb, y.rgb) and np.array_equal(x.depth, y.depth)
        assert np.array_equal(x.pose_gt, y.pose_gt)
    assert np.array_equal(a[4].depth, fa[4].depth)  # random access equals iteration
    assert not np.array_equal(fa[1].rgb, fc[1].rgb)
    assert not np.array_equal(fa[1].depth, fc[1].depth)


@pytest.mark.parametrize("name", sorted(TRAJECTORIES))
def test_trajectories_are_realistic_and_revisit_their_start(scene, name):
    traj = make_trajectory(name, 300, seed=0)
    assert traj.poses.shape == (300, 7) and traj.poses.dtype == torch.float64
    dt = traj.timestamps[1:] - traj.timestamps[:-1]
    assert torch.allclose(dt, torch.full_like(dt, 1 / 30), atol=2e-6)
    lin, ang = trajectory_rates(traj)
    assert lin.max() <= 1.0 and ang.max() <= 60.0, (float(lin.max()), float(ang.max()))
    # smooth: no jerks between consecutive frame-to-frame motions
    assert (lin[1:] - lin[:-1]).abs().max() < 0.1
    # never inside an object nor nearer than 0.5 m to any surface
    assert free_space_distance(scene, traj.poses[:, :3].float()).min() > 0.5
    # a real revisit: some frame in the last 15 % sees the start from nearly the same pose
    tail = traj.poses[int(0.85 * 300):]
    rel = se3_between(traj.poses[:1].expand_as(tail), tail)
    dist = rel[:, :3].norm(dim=-1)
    angle = torch.rad2deg(so3_log(rel[:, 3:]).norm(dim=-1))
    close = (dist < 0.2) & (angle < 10.0)
    assert close.any(), (float(dist.min()), float(angle.min()))
    assert not ((dist < 1e-3) & (angle < 0.05)).all()  # not just a copy of the start


def test_trajectories_look_at_the_scene(scene):
    K = torch.from_numpy(synthetic_intrinsics(64, 48))
    for name in TRAJECTORIES:
        traj = make_trajectory(name, 24)
        depth = render_frames(scene, K, traj.poses, 48, 64).depth
        med = depth.reshape(24, -1).median(dim=1).values
        assert med.min() > 1.0 and med.max() < 4.5, (name, float(med.min()), float(med.max()))


def test_too_fast_trajectory_warns(caplog):
    with caplog.at_level(logging.WARNING, logger="slam.synthetic.trajectories"):
        traj = make_trajectory("loop", 60)
    assert "too fast" in caplog.text
    assert trajectory_rates(traj)[0].max() > 1.0


def test_depth_noise_statistics_and_invalid_pixels():
    z0 = 2.0
    depth = torch.full((1, 200, 200), z0)
    cos = torch.ones_like(depth)
    cfg = DepthNoiseConfig(disparity_step=0.0, dropout=0.0)
    noisy = apply_depth_noise(depth, cos, cfg, [7])
    sigma = cfg.sigma_base + cfg.sigma_quad * (z0 - cfg.sigma_ref) ** 2
    assert abs(float((noisy - z0).std()) / sigma - 1.0) < 0.05
    assert abs(float((noisy - z0).mean())) < 4 * sigma / 200
    # disparity quantisation: depths take the values f*b / (k / 8)
    q = apply_depth_noise(depth, cos, DepthNoiseConfig(dropout=0.0), [7])
    disp = cfg.focal_baseline / q[q > 0]
    assert torch.allclose(disp * 8, (disp * 8).round(), atol=1e-3)
    # holes, range limits, grazing angles and occluding edges read as 0
    d = torch.full((1, 64, 64), 1.5)
    d[0, :, :8] = 0.3  # too near (and an occluding edge next to it)
    cos = torch.ones_like(d)
    cos[0, :4] = 0.05  # grazing
    out = apply_depth_noise(d, cos, DepthNoiseConfig(dropout=0.05), [1])
    assert (out[0, :, :8] == 0).all() and (out[0, :4] == 0).all() and (out[0, :, 8] == 0).all()
    frac = float((out[0, 4:, 12:] == 0).float().mean())
    assert 0.01 < frac < 0.12  # 5 % of 4x4 blobs dropped
    assert torch.equal(out, apply_depth_noise(d, cos, DepthNoiseConfig(dropout=0.05), [1]))


def test_depth_distortion_and_correlated_noise():
    """The fixed disparity pattern gives exactly ``z = fb / (fb / z0 + d r^2)`` (0 at the centre, d at the
    corners) in every frame; correlated noise keeps the std sigma(z) but neighbouring pixels share it."""
    z0, n = 2.5, 101
    depth = torch.full((2, n, n), z0)
    cos = torch.ones_like(depth)
    quiet = {"sigma_base": 0.0, "sigma_quad": 0.0, "disparity_step": 0.0, "dropout": 0.0}
    out = apply_depth_noise(depth, cos, DepthNoiseConfig(disparity_distortion=0.3, **quiet), [1, 2])
    fb = DepthNoiseConfig().focal_baseline
    assert abs(float(out[0, n // 2, n // 2]) - z0) < 1e-5  # the centre is unbiased
    assert float(out[0, 0, 0]) == pytest.approx(fb / (fb / z0 + 0.3), rel=1e-5)  # the corners: the whole d
    assert float(out[0, 0, n // 2]) == pytest.approx(fb / (fb / z0 + 0.15), rel=1e-5)  # an edge's middle: d / 2
    assert z0 - float(out[0, 0, 0]) > 0.04  # 4 cm nearer at 2.5 m: a bias odometry cannot average out
    assert torch.equal(out[0], out[1])  # a fixed pattern: the same in every frame
    cfg = DepthNoiseConfig(disparity_step=0.0, dropout=0.0, noise_correlation_px=2.0)
    big = torch.full((1, 200, 200), 2.0)
    e = apply_depth_noise(big, torch.ones_like(big), cfg, [7])[0] - 2.0
    sigma = cfg.sigma_base + cfg.sigma_quad * (2.0 - cfg.sigma_ref) ** 2
    assert abs(float(e.std()) / sigma - 1.0) < 0.15
    lag1 = float((e[:, 1:] * e[:, :-1]).mean() / e.var())  # Gaussian sigma 2 px: exp(-1 / 16) = 0.94
    assert 0.85 < lag1 < 0.99, lag1
    flat = DepthNoiseConfig(disparity_step=0.0, dropout=0.0)
    white = apply_depth_noise(big, torch.ones_like(big), flat, [7])[0] - 2.0
    assert abs(float((white[:, 1:] * white[:, :-1]).mean() / white.var())) < 0.05


def test_motion_blur_is_the_average_over_the_exposure(scene, K):
    """The screen-space blur against its definition: the frames rendered at the instants of the exposure
    and averaged. A camera moving 6 cm and panning 3 deg per frame, exposure 0.6 of the interval."""
    from slam.lie import se3_compose, se3_exp

    base = make_trajectory("loop", num_frames=300, seed=0).poses[40:41]
    step = se3_exp(torch.tensor([[0.06, 0.0, 0.0, 0.0, math.radians(3.0), 0.0]], dtype=torch.float64))
    before, after = se3_compose(base, se3_inv(step)), se3_compose(base, step)
    sharp = render_frames(scene, K, base, H, W)
    blur = apply_motion_blur(sharp.rgb, sharp.depth, K, base, before, after, 0.6, samples=9)
    # the reference: 9 renders along the geodesic from the previous to the next pose, averaged
    inst = [se3_compose(base, se3_exp(f * se3_log_(step))) for f in np.linspace(-0.3, 0.3, 9)]
    ref = render_frames(scene, K, torch.cat(inst), H, W).rgb.float().mean(0)
    m = 8  # the borders see what the sharp frame does not
    err = (blur[0].float() - ref)[m:-m, m:-m].abs()
    moved = (sharp.rgb[0].float() - ref)[m:-m, m:-m].abs()
    assert float(moved.mean()) > 10.0  # the blur is visible (measured 17 grey levels)
    # measured 1.3 grey levels (where the motion uncovers surfaces the sharp frame hides)
    assert float(err.mean()) < 0.12 * float(moved.mean()), (float(err.mean()), float(moved.mean()))
    assert float(err.median()) < 1.5
    # no exposure: the sharp frame itself; bad shapes are refused
    assert torch.equal(apply_motion_blur(sharp.rgb, sharp.depth, K, base, before, after, 0.0), sharp.rgb)
    with pytest.raises(ValueError, match="before"):
        apply_motion_blur(sharp.rgb, sharp.depth, K, base, before[:0], after, 0.5)
    with pytest.raises(ValueError, match="exposure_time"):
        ImageNoiseConfig(exposure_time=-1.0)


def se3_log_(pose):
    from slam.lie import se3_log

    return se3_log(pose)


def test_image_noise_is_small_and_seeded():
    rgb = torch.full((2, 50, 50, 3), 100, dtype=torch.uint8)
    out = apply_image_noise(rgb, ImageNoiseConfig(), [1, 2])
    diff = out.float() - 100
    assert 0.5 < float(diff[0].std()) < 3.0
    assert abs(float(diff.mean())) < 15
    assert torch.equal(out, apply_image_noise(rgb, ImageNoiseConfig(), [1, 2]))
    assert not torch.equal(out[0], out[1])


def _every_box_hits(origins, dirs, scene):
    """Nearest hits ``(M,)`` t, box, face of world rays ``(M, 3)``, every ray tested against every box."""
    from slam.synthetic.render import _slab

    t_best = torch.full((origins.shape[0],), float("inf"))
    box = torch.zeros(origins.shape[0], dtype=torch.int64)
    face = torch.zeros_like(box)
    for b in range(scene.num_boxes):
        R = scene.rotations[b]
        t, f = _slab(R.T @ (origins - scene.centers[b]).T, R.T @ dirs.T, scene.half_sizes[b][:, None],
                     bool(scene.inside[b]))
        better = t < t_best
        t_best, box, face = torch.where(better, t, t_best), torch.where(better, b, box), torch.where(better, f, face)
    return t_best, box, face


def test_screen_space_culling_matches_every_box_tested(scene, K):
    traj = make_trajectory("loop", 50)
    out = render_frames(scene, K, traj.poses[10], H, W)
    from slam.lie import quat_to_rotmat
    from slam.synthetic.render import pixel_rays
    R = quat_to_rotmat(traj.poses[10, 3:]).float()
    dirs = pixel_rays(K, H, W).float() @ R.T
    origins = traj.poses[10, :3].float().expand_as(dirs)
    t, box, face = _every_box_hits(origins, dirs, scene)
    assert torch.allclose(t.reshape(H, W), out.depth[0], atol=1e-5)
    assert torch.equal((box * 6 + face).reshape(H, W), out.hit[0])


def test_procedural_fallback_without_scikit_image(monkeypatch, caplog):
    monkeypatch.setattr(scene_mod, "_skimage_data_dir", lambda: None)
    scene_mod._load_photos_cached.cache_clear()
    try:
        with caplog.at_level(logging.WARNING, logger="slam.synthetic.scene"):
            sc = build_room_scene(RoomConfig(texel_density=16.0, object_texel_density=16.0))
    finally:
        scene_mod._load_photos_cached.cache_clear()
    assert "procedural" in caplog.text
    assert sc.num_boxes == 10
    tex = sc.tex_buffer.float()
    assert tex.std() > 20  # textured, not flat


def test_photographs_load_offline():
    photos = scene_mod.load_photo_textures()
    if scene_mod._skimage_data_dir() is None:
        pytest.skip("scikit-image is not installed")
    assert set(photos) == set(scene_mod.PHOTO_FILES)
    assert photos["astronaut"].shape == (512, 512, 3) and photos["camera"].shape == (512, 512, 3)


def test_bad_inputs_raise_clear_errors(scene, K):
    with pytest.raises(ValueError, match=r"\(N, 7\)"):
        render_frames(scene, K, torch.zeros(2, 6), H, W)
    with pytest.raises(ValueError, match="K must have shape"):
        render_frames(scene, torch.eye(4), torch.zeros(7), H, W)
    with pytest.raises(ValueError, match="unknown trajectory"):
        make_trajectory("spiral", 10)
    with pytest.raises(ValueError, match="need one seed per frame"):
        apply_depth_noise(torch.ones(2, 4, 4), torch.ones(2, 4, 4), DepthNoiseConfig(), [1])


def test_room_geometry_helpers(scene):
    centre = torch.tensor([[3.5, 3.0, 1.4]])
    # the room's centre is 1.4 m from the ceiling and floor, farther from the walls and objects
    assert scene.surface_distance(centre).item() == pytest.approx(1.4, abs=1e-5)
    assert free_space_distance(scene, centre).item() == pytest.approx(1.4, abs=1e-5)
    outside = torch.tensor([[-1.0, 3.0, 1.0]])
    assert free_space_distance(scene, outside).item() < 0
    assert math.isclose(scene.room_size[0], 7.0)
