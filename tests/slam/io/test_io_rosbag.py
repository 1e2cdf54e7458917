"""ROS bag reader: bags written with rosbags' own writer (ROS1 and ROS2), read back frame by frame."""
from __future__ import annotations

import sys
import tracemalloc

import numpy as np
import pytest
from helpers import TUM_BAG_TOPICS, write_rgbd_bag

from slam.io import DatasetError, open_sequence
from slam.io.trajectory import Trajectory, write_tum_trajectory

pytest.importorskip("rosbags", reason="needs attnloop[rosbag]")

H, W = 24, 32
K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])


def _frame(k: int):
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 10 * k, 100, 200  # red marks the frame, blue tells RGB from BGR
    depth = np.full((H, W), 1.0 + 0.25 * k, np.float32)
    depth[0, :5] = 0.0  # no depth
    return rgb, depth


def _frames(n: int):
    return [(k / 30, *_frame(k)) for k in range(n)]


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
@pytest.mark.parametrize("rgb_encoding,depth_encoding", [("rgb8", "32FC1"), ("bgr8", "16UC1"), ("mono8", "32FC1")])
def test_frames_read_back(tmp_path, ros2, rgb_encoding, depth_encoding):
    path = write_rgbd_bag(tmp_path / ("bag" if ros2 else "x.bag"), _frames(4), K, ros2=ros2,
                          rgb_encoding=rgb_encoding, depth_encoding=depth_encoding)
    seq = open_sequence(path)
    assert len(seq) == 4 and seq.name == ("bag" if ros2 else "x")
    np.testing.assert_array_equal(seq.K, K)
    np.testing.assert_allclose(seq.timestamps, np.arange(4) / 30, atol=1e-9)
    for k in (2, 0, 3):  # a step back too
        frame = seq[k]
        rgb, depth = _frame(k)
        want = np.repeat(rgb[..., :1], 3, axis=2) if rgb_encoding == "mono8" else rgb
        np.testing.assert_array_equal(frame.rgb, want)
        assert frame.depth.dtype == np.float32 and frame.depth[0, :5].tolist() == [0.0] * 5  # NaN / 0: no depth
        np.testing.assert_array_equal(frame.depth, depth)
        assert frame.pose_gt is None


def test_colour_and_depth_paired_by_stamp_as_tum(tmp_path):
    # rgb at 0.0 0.1 0.2 0.3; depth 12 ms after the first, 25 ms after the second (beyond TUM's 20 ms), 10 ms
    # before the third, 5 ms after the fourth: frames 0, 2, 3 with their own depth
    offsets = (0.012, 0.025, -0.010, 0.005)
    frames = [(0.1 * k, *_frame(k), 0.1 * k + offsets[k]) for k in range(4)]
    seq = open_sequence(write_rgbd_bag(tmp_path / "x.bag", frames, K))
    np.testing.assert_allclose(seq.timestamps, [0.0, 0.2, 0.3], atol=1e-9)
    np.testing.assert_allclose(seq.depth_timestamps, [0.012, 0.19, 0.305], atol=1e-9)
    for i, k in enumerate((0, 2, 3)):
        assert seq[i].rgb[0, 0, 0] == 10 * k and seq[i].depth[5, 5] == np.float32(1.0 + 0.25 * k)


def test_the_kitchen_frames_as_the_folder_reader_gives_them(tmp_path, redkitchen_dir):
    kitchen = open_sequence(redkitchen_dir)
    frames = ((k / 30, kitchen[k].rgb, kitchen[k].depth) for k in range(3))
    seq = open_sequence(write_rgbd_bag(tmp_path / "k.bag", frames, kitchen.K))
    for k in range(3):
        np.testing.assert_array_equal(seq[k].rgb, kitchen[k].rgb)
        np.testing.assert_array_equal(seq[k].depth, kitchen[k].depth)


def test_ground_truth_file_paired_with_the_frames(tmp_path):
    path = write_rgbd_bag(tmp_path / "x.bag", _frames(4), K)
    # poses at the frames' times but the second (50 ms away: beyond 20 ms)
    import torch

    stamps = torch.tensor([0.0, 1 / 30 + 0.05, 2 / 30 + 0.004, 3 / 30], dtype=torch.float64)
    poses = torch.zeros(4, 7, dtype=torch.float64)
    poses[:, 0], poses[:, 6] = torch.arange(4, dtype=torch.float64), 1.0
    write_tum_trajectory(tmp_path / "gt.txt", Trajectory(stamps, poses))
    seq = open_sequence(path, groundtruth=tmp_path / "gt.txt")
    assert [None if p is None else p[0] for p in (seq[k].pose_gt for k in range(4))] == [0.0, None, 2.0, 3.0]
    assert len(seq.groundtruth) == 3


def _peak_bytes_reading(path) -> tuple[int, int]:
    """Frames read and the peak traced bytes of opening ``path`` and reading every frame."""
    tracemalloc.start()
    try:
        seq = open_sequence(path)
        n = sum(1 for _ in seq)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    seq.close()
    return n, peak


def test_memory_does_not_grow_with_the_bag(tmp_path):
    rgb, depth = np.zeros((120, 160, 3), np.uint8), np.ones((120, 160), np.float32)
    frame_bytes = rgb.nbytes + depth.nbytes
    paths = [write_rgbd_bag(tmp_path / f"{n}.bag", ((k / 30, rgb, depth) for k in range(n)), K) for n in (20, 80)]
    _peak_bytes_reading(paths[0])  # imports and rosbags' type generation, once
    (n_short, short), (n_long, long) = (_peak_bytes_reading(p) for p in paths)
    assert (n_short, n_long) == (20, 80)
    # 60 frames more held would be 60 frames' bytes more; a ROS1 chunk (~1 MB, 7 of these frames) is read whole
    assert long - short < 8 * frame_bytes, f"{(long - short) / frame_bytes:.1f} frames' bytes more for 60 frames more"


@pytest.mark.parametrize("case,expected", [
    ("topic", "no topic /camera/depth/image (the bag has: /camera/rgb/camera_info, /camera/rgb/image_color, /d)"),
    ("encoding", "/camera/rgb/image_color: unsupported image encoding 'yuv422' (expected rgb8, bgr8, mono8)"),
    ("truncated", "not a readable ROS bag: truncated or corrupt"),
    ("no_info", "no topic /camera/rgb/camera_info"),
])
def test_bad_bags_name_what_is_wrong(tmp_path, case, expected):
    topics = (TUM_BAG_TOPICS[0], "/d", TUM_BAG_TOPICS[2]) if case == "topic" else TUM_BAG_TOPICS
    if case == "no_info":
        topics = (*TUM_BAG_TOPICS[:2], "/info")
    path = write_rgbd_bag(tmp_path / "x.bag", _frames(3), K, topics=topics,
                          rgb_encoding="yuv422" if case == "encoding" else "rgb8")
    if case == "truncated":
        path.write_bytes(path.read_bytes()[:-200])
    with pytest.raises(DatasetError) as e:
        open_sequence(path)
    assert str(e.value).startswith(f"{path}: ") and expected in str(e.value)
    assert "\n" not in str(e.value)


def test_a_truncated_ros2_bag_names_its_folder(tmp_path):
    path = write_rgbd_bag(tmp_path / "bag", _frames(3), K, ros2=True)
    (db,) = path.glob("*.db3")
    db.write_bytes(db.read_bytes()[: db.stat().st_size // 2])
    with pytest.raises(DatasetError) as e:
        open_sequence(path)
    assert str(e.value).startswith(f"{path}: not a readable ROS bag: truncated or corrupt")


def test_bag_options_refused_on_a_folder(tmp_path):
    with pytest.raises(DatasetError, match="--depth-topic applies to a ROS bag"):
        open_sequence(tmp_path, depth_topic="/d")


def test_without_rosbags_the_extra_is_named(tmp_path, monkeypatch):
    path = write_rgbd_bag(tmp_path / "x.bag", _frames(2), K)
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    with pytest.raises(DatasetError, match=r"pip install attnloop\[rosbag\]"):
        open_sequence(path)


def test_intrinsics_and_depth_scale_options(tmp_path):
    path = write_rgbd_bag(tmp_path / "x.bag", _frames(2), K)
    # TUM's fr1 camera (517.3 516.5 318.6 255.3) or given intrinsics replace the camera info's
    assert open_sequence(path, camera="fr1").K[0].tolist() == [517.3, 0.0, 318.6]
    given = np.array([[500.0, 0.0, 300.0], [0.0, 501.0, 200.0], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(open_sequence(path, K=given).K, given)
    with pytest.raises(DatasetError, match="depth_scale .* applies to 16UC1 depth; /camera/depth/image is 32FC1"):
        open_sequence(path, depth_scale=5000)
    mm = write_rgbd_bag(tmp_path / "mm.bag", _frames(2), K, depth_encoding="16UC1")
    # 16UC1 read at TUM's 5000 units per metre: 1 m of millimetres is 0.2 m, refused by the unit check
    with pytest.raises(DatasetError, match="--depth-scale 1000"):
        open_sequence(mm, depth_scale=5000)
    assert open_sequence(mm, depth_scale=5000, check_units=False)[0].depth[5, 5] == np.float32(0.2)
