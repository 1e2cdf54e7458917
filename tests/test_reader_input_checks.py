"""Input checks of the sequence readers and the synthetic writer: frame-name collisions, fps, camera names,
and the documented TUM ground-truth association."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from slam.io import DatasetError, SevenScenesSequence, TUMSequence, open_sequence
from slam.io.trajectory import Trajectory
from slam.io.tum import tum_camera
from slam.synthetic.sequence import _tiny_scene, generate_sequence

H, W = 24, 32


def _custom_trajectory(stamps) -> Trajectory:
    poses = torch.zeros(len(stamps), 7, dtype=torch.float64)
    poses[:, 0] = torch.arange(len(stamps), dtype=torch.float64) * 0.01  # distinct positions
    poses[:, 6] = 1.0
    return Trajectory(torch.tensor(stamps, dtype=torch.float64), poses)


def _write_7scenes(root, numbers=(0, 1, 2)):
    root.mkdir(parents=True)
    for k in numbers:
        cv2.imwrite(str(root / f"frame-{k:06d}.color.png"), np.full((H, W, 3), 10 * k, np.uint8))
        cv2.imwrite(str(root / f"frame-{k:06d}.depth.png"), np.full((H, W), 1500, np.uint16))
    return root


def _write_tum(root, rgb_stamps, gt_stamps=None):
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines = ["# color images\n"], ["# depth maps\n"]
    for k, t in enumerate(rgb_stamps):
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), np.full((H, W, 3), 10 + k, np.uint8))
        cv2.imwrite(str(root / "depth" / f"{t:.6f}.png"), np.full((H, W), 5000, np.uint16))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png\n")
        depth_lines.append(f"{t:.6f} depth/{t:.6f}.png\n")
    (root / "rgb.txt").write_text("".join(rgb_lines))
    (root / "depth.txt").write_text("".join(depth_lines))
    if gt_stamps is not None:
        (root / "groundtruth.txt").write_text(
            "# timestamp tx ty tz qx qy qz qw\n" + "".join(f"{t:.6f} {k + 1} 0 0 0 0 0 1\n"
                                                          for k, t in enumerate(gt_stamps)))
    return root


# --- generate_sequence: frame file names -------------------------------------------------------------------


def test_generate_sequence_refuses_colliding_frame_names(tmp_path):
    out = tmp_path / "seq"
    traj = _custom_trajectory([0.0, 1e-7, 0.2, 0.1, 0.3, 0.4])  # frames 0 and 1 are both "0.000000.png"
    with pytest.raises(ValueError) as info:
        generate_sequence(out, traj, width=W, height=H, scene=_tiny_scene(), workers=1)
    msg = str(info.value)
    assert "frames 0 and 1" in msg and "0.000000" in msg and "1 microsecond" in msg
    assert not out.exists()  # refused before anything was written


def test_generate_sequence_refuses_signed_zero_collision(tmp_path):
    # "-0.000000" and "0.000000" are different file names but the same timestamp in rgb.txt
    traj = _custom_trajectory([-1e-7, 0.0, 0.1])
    with pytest.raises(ValueError, match=r"frames 0 and 1 .*0\.000000"):
        generate_sequence(tmp_path / "seq", traj, width=W, height=H, scene=_tiny_scene(), workers=1)
    assert not (tmp_path / "seq").exists()


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_generate_sequence_refuses_non_finite_stamps(tmp_path, bad):
    traj = _custom_trajectory([0.0, 0.1, bad, 0.3])
    with pytest.raises(ValueError) as info:
        generate_sequence(tmp_path / "seq", traj, width=W, height=H, scene=_tiny_scene(), workers=1)
    assert "non-finite" in str(info.value) and "frame 2" in str(info.value) and repr(bad) in str(info.value)
    assert not (tmp_path / "seq").exists()


def test_generate_sequence_keeps_close_but_distinct_stamps(tmp_path):
    # 1 microsecond apart still gives distinct names; unsorted stamps are allowed as before
    traj = _custom_trajectory([0.0, 1e-6, 0.2, 0.1])
    out = generate_sequence(tmp_path / "seq", traj, width=W, height=H, scene=_tiny_scene(), workers=1)
    assert sorted(p.name for p in (out / "rgb").iterdir()) == [
        "0.000000.png", "0.000001.png", "0.100000.png", "0.200000.png"]
    seq = TUMSequence(out)
    assert len(seq) == 4 and np.allclose(seq.timestamps, [0.0, 1e-6, 0.1, 0.2], rtol=0, atol=1e-9)


# --- 7-Scenes fps ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("fps", [0, 0.0, -30, -30.0, math.nan, math.inf, True, "30", None])
def test_sevenscenes_refuses_bad_fps(tmp_path, fps):
    root = _write_7scenes(tmp_path / "seq-01")
    with pytest.raises(DatasetError) as info:
        SevenScenesSequence(root, fps=fps)
    assert info.value.path == str(root)
    assert f"fps must be a finite positive number, got {fps!r}" in str(info.value)
    with pytest.raises(DatasetError, match="fps must be"):
        open_sequence(root, fps=fps)


def test_sevenscenes_refuses_subnormal_fps(tmp_path):
    root = _write_7scenes(tmp_path / "seq-01")
    with pytest.raises(DatasetError) as info:
        SevenScenesSequence(root, fps=1e-320)  # positive and finite, but k / fps overflows
    assert info.value.path == str(root) and "fps=1e-320 is too small: frame 2 would be at inf s" in str(info.value)


@pytest.mark.parametrize("fps", [30, 15.0, np.float32(10.0), np.int64(5)])
def test_sevenscenes_accepts_positive_fps(tmp_path, fps):
    seq = SevenScenesSequence(_write_7scenes(tmp_path / "seq-01", (0, 1, 3)), fps=fps)
    assert seq.timestamps.dtype == np.float64
    assert np.array_equal(seq.timestamps, np.array([0, 1, 3], np.float64) / float(fps))


# --- TUM camera names --------------------------------------------------------------------------------------


def test_tum_unknown_camera_names_the_folder(tmp_path):
    root = _write_tum(tmp_path / "my_sequence", [1.0])
    with pytest.raises(DatasetError) as info:
        TUMSequence(root, camera="fr4")
    assert info.value.path == str(root)
    assert str(info.value) == f"{root}: unknown TUM camera 'fr4'; expected one of fr1, fr2, fr3, ros"
    with pytest.raises(DatasetError) as info:
        open_sequence(root, camera="fr4")
    assert info.value.path == str(root) and "unknown TUM camera 'fr4'" in str(info.value)


def test_tum_camera_on_its_own():
    assert tum_camera("freiburg2").fx == 520.9 and tum_camera("ROS").fx == 525.0
    with pytest.raises(ValueError) as info:
        tum_camera("fr4")
    assert not isinstance(info.value, DatasetError)  # a bad argument, not a bad dataset folder
    assert str(info.value) == "unknown TUM camera 'fr4'; expected one of fr1, fr2, fr3, ros"


# --- TUM ground-truth association --------------------------------------------------------------------------


def test_tum_groundtruth_is_greedy_one_to_one(tmp_path):
    # 1.000 and 1.010 are both 0.005 s from the 1.005 pose; the first takes it, so 1.010 gets none (a pose
    # is not shared), and 1.030 is 0.025 s from 1.005 and 0.07 s from 1.100: none either.
    root = _write_tum(tmp_path / "fr1_assoc", [1.000, 1.010, 1.030], gt_stamps=[1.005, 1.100])
    seq = TUMSequence(root)
    assert np.array_equal(seq.groundtruth_pose(0), [1, 0, 0, 0, 0, 0, 1])
    assert seq.groundtruth_pose(1) is None and seq.groundtruth_pose(2) is None
    assert seq[1].pose_gt is None
    gt = seq.groundtruth
    assert gt.timestamps.tolist() == [1.0] and gt.poses[0, 0].item() == 1.0
