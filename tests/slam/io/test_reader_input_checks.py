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


# --- units: timestamps by their spacing, depth by its median ------------------------------------------------


@pytest.mark.parametrize("stamps, unit, per_second", [
    ([1.7e9 + k / 30 for k in range(5)], "seconds", 1.0),
    ([k * 0.1 for k in range(5)], "seconds", 1.0),  # 10 Hz from 0
    ([2.0 * k for k in range(5)], "seconds", 1.0),  # every 2 s: slow, but seconds
    ([1.7e12 + 33.3 * k for k in range(5)], "milliseconds", 1e3),
    ([1.7e15 + 33333.0 * k for k in range(5)], "microseconds", 1e6),
    ([1.7e18 + 33333333.0 * k for k in range(5)], "nanoseconds", 1e9),
    ([1e7 * k for k in range(5)], "nanoseconds", 1e9),  # 100 Hz, from 0
    ([0, 1, 2, 3, 4], "frame numbers", None),
    ([5.0], "seconds", 1.0),
])
def test_timestamp_unit_from_the_spacing(stamps, unit, per_second):
    from slam.input_checks import timestamp_unit

    found, factor, _ = timestamp_unit(np.array(stamps))
    assert (found, factor) == (unit, per_second)


@pytest.mark.parametrize("per_second", [1000, 10 ** 6, 10 ** 9])
def test_tum_stamps_in_sub_second_units_are_read_as_seconds(tmp_path, per_second, caplog):
    secs = [1.0 + k / 30 for k in range(4)]
    plain = _write_tum(tmp_path / "s", secs, gt_stamps=secs)
    scaled = _write_tum(tmp_path / "x", secs, gt_stamps=secs)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        lines = [ln if ln.startswith("#") else f"{round(float(ln.split()[0]) * per_second)} {ln.split(maxsplit=1)[1]}"
                 for ln in (scaled / name).read_text().splitlines()]
        (scaled / name).write_text("\n".join(lines) + "\n")
    a, b = TUMSequence(plain), TUMSequence(scaled)
    step = 0.5 / per_second + 1e-9  # the stamps were rounded to whole units
    np.testing.assert_allclose(b.timestamps, a.timestamps, rtol=0, atol=step)
    np.testing.assert_allclose(b.groundtruth.timestamps.numpy(), a.groundtruth.timestamps.numpy(), rtol=0, atol=step)
    assert len(b) == 4 and b.groundtruth_pose(3) is not None
    unit = {1000: "milliseconds", 10 ** 6: "microseconds", 10 ** 9: "nanoseconds"}[per_second]
    notices = [r.getMessage() for r in caplog.records if "converted to seconds" in r.getMessage()]
    hz = "30.3" if per_second == 1000 else "30"  # whole milliseconds: 33 apart
    assert len(notices) == 1 and f"rgb.txt in {unit} ({hz} Hz)" in notices[0], notices


def test_tum_frame_numbers_for_stamps_are_refused_with_the_fix(tmp_path):
    root = _write_tum(tmp_path / "seq", [0.0, 1.0, 2.0])
    with pytest.raises(DatasetError, match=r"rgb\.txt: the timestamps are frame numbers .* / 30 at 30 Hz"):
        TUMSequence(root)


def test_depth_at_the_wrong_scale_is_refused_naming_the_right_one(tmp_path):
    root = _write_7scenes(tmp_path / "seq")  # 1500 mm everywhere
    assert SevenScenesSequence(root)[0].depth[0, 0] == 1.5
    with pytest.raises(DatasetError, match=r"median of 0\.3 m .*outside the 0\.5-20 m.*millimetres\? give "
                                           r"--depth-scale 1000 .*puts it at 1\.5 m"):
        SevenScenesSequence(root, depth_scale=5000)
    with pytest.raises(DatasetError, match=r"median of 1\.5e\+03 m .*--depth-scale 1000"):
        open_sequence(root, depth_scale=1)
    tum = _write_tum(tmp_path / "tum", [1.0, 1.1])  # 5000 units: 1 m
    with pytest.raises(DatasetError, match=r"median of 0\.2 m") as info:
        TUMSequence(tum, depth_scale=25000)  # 0.2 m: too near; both known scales fit, 1 m nearest a room's 2 m
    assert str(info.value).endswith("TUM's 1/5000 m? give --depth-scale 5000 (depth_scale=5000 in Python), which puts "
                                    "it at 1 m or millimetres? give --depth-scale 1000 (depth_scale=1000 in Python), "
                                    "which puts it at 5 m (--no-depth-check if the scene really is that near or far)")


def test_the_depth_check_leaves_unreadable_and_empty_depth_to_the_run(tmp_path):
    root = _write_7scenes(tmp_path / "zeros")
    for k in range(3):
        cv2.imwrite(str(root / f"frame-{k:06d}.depth.png"), np.zeros((H, W), np.uint16))
    assert len(SevenScenesSequence(root, depth_scale=5000)) == 3  # nothing valid: nothing to judge
    root = _write_7scenes(tmp_path / "bad")
    for k in range(3):
        (root / f"frame-{k:06d}.depth.png").write_bytes(b"not a png")
    assert len(SevenScenesSequence(root)) == 3  # the run reports unreadable frames, one by one


def test_fast_ground_truth_in_nanoseconds_takes_the_unit_that_meets_the_frames(tmp_path, caplog):
    """Motion capture at 200 Hz in nanoseconds is spaced 5e6 apart, like a camera's microseconds: the unit
    that puts it within the frames' span is the one taken."""
    secs = [1.0 + k / 30 for k in range(4)]
    root = _write_tum(tmp_path / "seq", secs)
    for name in ("rgb.txt", "depth.txt"):
        lines = [ln if ln.startswith("#") else f"{round(float(ln.split()[0]) * 1e9)} {ln.split(maxsplit=1)[1]}"
                 for ln in (root / name).read_text().splitlines()]
        (root / name).write_text("\n".join(lines) + "\n")
    gt = [1.0 + k / 200 for k in range(30)]
    (root / "groundtruth.txt").write_text("".join(f"{round(t * 1e9)} {k} 0 0 0 0 0 1\n" for k, t in enumerate(gt)))
    seq = TUMSequence(root)
    np.testing.assert_allclose(seq.groundtruth_trajectory.timestamps.numpy(), gt, rtol=0, atol=1e-9)
    assert seq.groundtruth_pose(0) is not None and seq.groundtruth_pose(3)[0] == 20  # 1.1 s: pose 20
    assert "groundtruth.txt in nanoseconds (200 Hz)" in caplog.text
