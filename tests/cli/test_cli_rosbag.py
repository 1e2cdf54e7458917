"""``attnloop-slam FILE.bag`` and a ROS2 bag folder: the kitchen's first 100 frames as a bag on TUM RGB-D's topics
track as the folder does; a bad bag is one line and exit code 2."""
from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from helpers import write_rgbd_bag

from slam.cli import main
from slam.io import open_sequence
from slam.io.trajectory import read_tum_trajectory, write_tum_trajectory

pytest.importorskip("rosbags", reason="needs attnloop[rosbag]")

N = 100
K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])


def _kitchen_bag(path, kitchen_dir, ros2: bool):
    kitchen = open_sequence(kitchen_dir)
    frames = ((k / 30, kitchen[k].rgb, kitchen[k].depth) for k in range(N))  # 32FC1 metres, NaN for no depth
    return write_rgbd_bag(path, frames, K, ros2=ros2)


@pytest.fixture(scope="module")
def folder_run(redkitchen_dir, tmp_path_factory):
    """``attnloop-slam KITCHEN --registered --max-frames 100``: its trajectory and metrics."""
    out = tmp_path_factory.mktemp("folder_run")
    assert main([str(redkitchen_dir), "--registered", "--max-frames", str(N), "--out", str(out), "--quiet"]) == 0
    return read_tum_trajectory(out / "trajectory.txt"), json.loads((out / "metrics.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
def test_kitchen_bag_tracks_as_the_folder(tmp_path, redkitchen_dir, folder_run, ros2):
    bag = _kitchen_bag(tmp_path / ("kitchen" if ros2 else "kitchen.bag"), redkitchen_dir, ros2)
    gt = open_sequence(redkitchen_dir)[:N].groundtruth  # stamped k / 30 as the frames
    write_tum_trajectory(tmp_path / "gt.txt", gt)
    out = tmp_path / "out"
    assert main([str(bag), "--ground-truth", str(tmp_path / "gt.txt"), "--out", str(out), "--quiet"]) == 0
    traj, metrics = read_tum_trajectory(out / "trajectory.txt"), json.loads((out / "metrics.json").read_text())
    want, want_metrics = folder_run
    assert len(traj) == len(want) == N
    np.testing.assert_allclose(traj.timestamps.numpy(), want.timestamps.numpy(), atol=1e-6)
    assert float((traj.poses[:, :3] - want.poses[:, :3]).norm(dim=1).max()) <= 1e-6
    assert float((traj.poses[:, 3:] - want.poses[:, 3:]).abs().max()) <= 1e-6
    # --ground-truth: the bag's run is evaluated as the folder's (whose ground truth is 7-Scenes' pose files)
    assert metrics["ate_rmse"] == pytest.approx(want_metrics["ate_rmse"], abs=1e-6)
    assert metrics["num_loops"] == want_metrics["num_loops"]


def _small_bag(path, **kwargs):
    rgb, depth = np.full((24, 32, 3), 90, np.uint8), np.full((24, 32), 1.5, np.float32)
    return write_rgbd_bag(path, [(k / 30, rgb, depth) for k in range(3)], K, **kwargs)


@pytest.mark.parametrize("case,expected", [
    ("topic", ("x.bag: no topic /camera/depth/image (the bag has: /camera/rgb/camera_info, /camera/rgb/image_color, "
               "/depth); name the topic with --depth-topic")),
    ("encoding", "x.bag: /camera/depth/image: unsupported image encoding '8UC1' (expected 32FC1, 16UC1)"),
    ("truncated", "x.bag: not a readable ROS bag: truncated or corrupt"),
])
def test_bad_bag_is_one_line(tmp_path, capsys, case, expected):
    path = tmp_path / "x.bag"
    if case == "topic":
        _small_bag(path, topics=("/camera/rgb/image_color", "/depth", "/camera/rgb/camera_info"))
    elif case == "encoding":
        _small_bag(path, depth_encoding="8UC1")
    else:
        _small_bag(path)
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    assert main([str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and expected in err, err


def test_topic_flags_select_the_topics(tmp_path, capsys):
    path = _small_bag(tmp_path / "x.bag", topics=("/c", "/d", "/i"))
    assert main([str(path), "--rgb-topic", "/c", "--depth-topic", "/x", "--out", str(tmp_path / "out")]) == 2
    assert "no topic /x" in capsys.readouterr().err  # --rgb-topic /c was found, the depth topic is the one named


def test_without_rosbags_the_extra_is_named(tmp_path, capsys, monkeypatch):
    path = _small_bag(tmp_path / "x.bag")
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    assert main([str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pip install attnloop[rosbag]" in err


def test_bag_flags_refused_on_a_folder(tmp_path, capsys, redkitchen_dir):
    assert main([str(redkitchen_dir), "--ground-truth", "gt.txt", "--out", str(tmp_path / "out")]) == 2
    assert "--ground-truth applies to a ROS bag" in capsys.readouterr().err
