"""The rerun recording of a run (``--rrd``, :mod:`slam.viewer`) read back with rerun's own reader and compared with
the run's outputs (trajectory.txt, loops.txt, metrics.json); the refusals without rerun installed."""
from __future__ import annotations

import json
import sys
from collections import defaultdict
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from slam.cli import main
from slam.io.trajectory import read_tum_trajectory
from slam.options import RunOptions, UsageError

DEMO = ["--demo", "--demo-frames", "120", "--demo-size", "320", "240", "--quiet"]


@pytest.fixture
def rerun_offline(tmp_path, monkeypatch):
    """rerun with its analytics off: a config saying so (what ``rerun analytics disable`` writes) in a config folder
    of the test's own, its data folder there too (checked empty after the run)."""
    rr = pytest.importorskip("rerun")
    config, data = tmp_path / "xdg-config", tmp_path / "xdg-data"
    (config / "rerun").mkdir(parents=True)
    (config / "rerun" / "analytics.json").write_text(json.dumps({
        "analytics_enabled": False, "analytics_id": "attnloop-tests", "metadata": {},
        "config_file_path": str(config / "rerun" / "analytics.json"),
        "data_dir_path": str(data / "rerun" / "analytics")}))
    monkeypatch.setenv("XDG_CONFIG_HOME", str(config))
    monkeypatch.setenv("XDG_DATA_HOME", str(data))
    yield rr
    assert not (data / "rerun" / "analytics").exists() or not any((data / "rerun" / "analytics").iterdir())


def _read(path) -> dict:
    """``{entity: {component: [(frame, value), ...]}}`` in logging order (a value logged again at a frame comes
    after the first: the one the viewer shows); static values at frame None."""
    from rerun.chunk import RrdReader

    rows = defaultdict(lambda: defaultdict(list))
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch().to_pydict()
        frames = batch.get("frame", [None] * chunk.num_rows)
        for name, values in batch.items():
            if ":" in name:
                for row_id, frame, value in zip(batch["rerun.controls.RowId"], frames, values):
                    rows[chunk.entity_path][name].append((row_id, frame, value))
    return {e: {c: [(f, v) for _, f, v in sorted(r, key=lambda x: x[0])] for c, r in comps.items()}
            for e, comps in rows.items()}


def _last_per_frame(rows) -> dict:
    return {f: v for f, v in rows}


@pytest.mark.slow
def test_recording_of_the_demo_holds_the_outputs(tmp_path, rerun_offline):
    out, rrd = tmp_path / "O", tmp_path / "run.rrd"
    assert main([*DEMO, "--out", str(out), "--rrd", str(rrd)]) == 0
    rec = _read(rrd)
    traj = read_tum_trajectory(out / "trajectory.txt")
    poses = traj.poses.numpy().astype(np.float32)
    metrics = json.loads((out / "metrics.json").read_text())

    cam = rec["/world/camera"]
    t = _last_per_frame(cam["Transform3D:translation"])
    q = _last_per_frame(cam["Transform3D:quaternion"])
    assert sorted(t) == list(range(120)) == sorted(q)
    np.testing.assert_array_equal(np.array([t[i][0] for i in range(120)], np.float32), poses[:, :3])
    np.testing.assert_array_equal(np.array([q[i][0] for i in range(120)], np.float32), poses[:, 3:])
    assert sorted(f for f, _ in cam["Image:buffer"]) == list(range(120))
    assert cam["Pinhole:resolution"] == [(None, [[320.0, 240.0]])]  # the demo's 320 x 240 logged as it is
    assert len(cam["Pinhole:image_from_camera"]) == 1

    # the map: one Points3D entity per keyframe, named by its frame, placed last at that frame's final pose
    stamps = traj.timestamps.numpy()
    keyframes = sorted(int(e.rsplit("/", 1)[1]) for e in rec if e.startswith("/world/map/"))
    assert len(keyframes) == metrics["num_keyframes"] > 10
    for k in keyframes:
        m = rec[f"/world/map/{k}"]
        points = np.array(m["Points3D:positions"][0][1])
        assert points.shape[1] == 3 and len(points) > 100 and (points[:, 2] > 0).all()
        np.testing.assert_array_equal(np.float32(m["Transform3D:translation"][-1][1][0]), poses[k, :3])
    # the keyframe path, last drawn through the keyframes' final positions
    path = np.array(rec["/world/trajectory"]["LineStrips3D:strips"][-1][1][0], np.float32)
    np.testing.assert_array_equal(path, poses[keyframes, :3])
    # one strip per accepted loop, between the final positions of its two keyframes
    loops = [[float(v) for v in ln.split()] for ln in (out / "loops.txt").read_text().splitlines() if ln[:1] != "#"]
    strips = rec["/world/loops"]["LineStrips3D:strips"][-1][1]
    assert len(strips) == len(loops) == metrics["num_loops"]
    for strip, (ta, tb) in zip(strips, loops):
        a, b = (int(np.argmin(np.abs(stamps - s))) for s in (ta, tb))
        np.testing.assert_array_equal(np.float32(strip), poses[[a, b], :3])
    assert len(rec["/stats/fps"]["Scalars:scalars"]) == 119 and len(rec["/stats/inliers"]["Scalars:scalars"]) == 120


def _state(i, new_keyframes=(), new_loops=(), correction=None):
    pose = torch.tensor([0.1 * i, 0, 0, 0, 0, 0, 1], dtype=torch.float64)
    return SimpleNamespace(index=i, pose=pose, num_inliers=50 + i, new_keyframes=list(new_keyframes),
                           new_loops=list(new_loops), correction=correction)


def test_a_correction_moves_the_keyframes_it_moved_and_redraws_the_loops(tmp_path, rerun_offline):
    """By hand: keyframes at frames 0, 2, 4; a loop 0-2 accepted at frame 4 with a correction that moves keyframe 1
    only; the final result moves keyframe 2 and keeps no loop."""
    from slam.io.frame import RGBDFrame
    from slam.viewer import RunViewer

    rr = rerun_offline
    rec = rr.RecordingStream("attnloop-test")
    rec.save(str(tmp_path / "v.rrd"))
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    depth = np.full((48, 64), 2.0, np.float32)
    depth[:8] = 0.0  # no depth: no points
    poses = torch.tensor([[0.0, 0, 0, 0, 0, 0, 1], [1, 0, 0, 0, 0, 0, 1], [2, 0, 0, 0, 0, 0, 1]], dtype=torch.float64)
    kfs = {0: 0, 2: 1, 4: 2}
    slam = SimpleNamespace(keyframes=[SimpleNamespace(frame_index=f) for f in kfs], made=0)
    slam.keyframe_poses = lambda: poses[:slam.made].clone()  # the keyframes made so far
    viewer = RunViewer(rec, max_image_width=32, map_stride=8)
    for i in range(5):
        frame = RGBDFrame(i, i / 30, np.full((48, 64, 3), 10 * i, np.uint8), depth, K)
        slam.made = sum(f <= i for f in kfs)
        if i == 4:
            poses[1, 1] = 0.5
        loop = SimpleNamespace(kf_a=0, kf_b=2)
        viewer.frame(frame, _state(i, [kfs[i]] if i in kfs else [], [loop] if i == 4 else [],
                                   object() if i == 4 else None), slam)
    final = poses.clone()
    final[2, 2] = -1.0
    traj = torch.tensor([[0.01 * i, 0, 0, 0, 0, 0, 1] for i in range(5)], dtype=torch.float64)
    viewer.finish(SimpleNamespace(num_frames=5, trajectory=SimpleNamespace(poses=traj), loops=[],
                                  keyframe_trajectory=SimpleNamespace(poses=final)))
    viewer.close()
    got = _read(tmp_path / "v.rrd")

    # the map entity of each keyframe: its points once, (48 - 8) / 8 x 64 / 8 = 5 x 8 of them, its transforms when moved
    for frame in kfs:
        m = got[f"/world/map/{frame}"]
        assert len(m["Points3D:positions"]) == 1 and np.array(m["Points3D:positions"][0][1]).shape == (40, 3)
    moves = {f: [(t, v[0]) for t, v in got[f"/world/map/{f}"]["Transform3D:translation"]] for f in kfs}
    assert moves[0] == [(0, [0.0, 0.0, 0.0])]
    assert moves[2] == [(2, [1.0, 0.0, 0.0]), (4, [1.0, 0.5, 0.0])]  # the correction at frame 4
    assert moves[4] == [(4, [2.0, 0.0, 0.0]), (4, [2.0, 0.0, -1.0])]  # placed at frame 4, moved by the final result
    loops = [(t, v) for t, v in got["/world/loops"]["LineStrips3D:strips"]]
    assert loops[-2] == (4, [[[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]]) and loops[-1] == (4, [])
    # the camera: the reported pose at each frame, then the final trajectory's; the image resized to 32 x 24
    t = _last_per_frame(got["/world/camera"]["Transform3D:translation"])
    np.testing.assert_allclose([t[i][0][0] for i in range(5)], [0.01 * i for i in range(5)], rtol=1e-6)
    assert got["/world/camera"]["Pinhole:resolution"] == [(None, [[32.0, 24.0]])]
    fx, _, _, _, fy, _, cx, cy, _ = got["/world/camera"]["Pinhole:image_from_camera"][0][1][0]
    assert (fx, fy, cx, cy) == (50.0, 50.0, 15.5, 11.5)  # (31.5 + 0.5) / 2 - 0.5: pixel centres scaled


def test_without_rerun_the_viewer_flags_exit_2_naming_the_extra(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun raises ImportError
    for flags in (["--rrd", str(tmp_path / "r.rrd")], ["--viewer"], ["--connect", "127.0.0.1:9876"]):
        out = tmp_path / "out"
        assert main([*DEMO, "--out", str(out), *flags]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"attnloop-slam: {flags[0]}: rerun is not installed; pip install 'attnloop[viewer]'"]
        assert not out.exists() and not (tmp_path / "r.rrd").exists()  # refused before any work


def test_viewer_settings_checked(tmp_path):
    from slam.viewer import check_viewer

    with pytest.raises(ValueError, match="--viewer spawns a viewer and --connect"):
        RunOptions(viewer=True, connect="127.0.0.1:9876")
    with pytest.raises(ValueError, match="RunOptions.rrd must be a non-empty string"):
        RunOptions(rrd="")
    pytest.importorskip("rerun")
    with pytest.raises(UsageError, match="--rrd .*: not a file in a writable folder"):
        check_viewer(RunOptions(rrd=str(tmp_path / "missing" / "r.rrd")))
    check_viewer(RunOptions(rrd=str(tmp_path / "r.rrd")))


def test_viewer_to_spawn_without_a_display_is_refused_before_the_work(tmp_path, capsys, monkeypatch):
    pytest.importorskip("rerun")
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main([*DEMO, "--out", str(tmp_path / "out"), "--viewer"]) == 2
    err = capsys.readouterr().err
    assert "--viewer: no display" in err and "--rrd FILE" in err and not (tmp_path / "out").exists()


@pytest.mark.slow
def test_a_viewer_that_never_answers_costs_the_run_nothing(tmp_path, rerun_offline, caplog):
    """--connect to an address where nothing listens (rerun gives up after ~8 s): a warning, and the run's outputs
    and its recording are written all the same."""
    out = tmp_path / "O"
    argv = ["--demo", "--demo-frames", "24", "--demo-size", "160", "120", "--no-loop", "--quiet", "--out", str(out),
            "--connect", "127.0.0.1:9", "--rrd", str(tmp_path / "r.rrd")]
    assert main(argv) == 0
    assert (out / "trajectory.txt").is_file() and (out / "metrics.json").is_file()
    assert "unable to connect" in caplog.text
    assert sorted(f for f, _ in _read(tmp_path / "r.rrd")["/world/camera"]["Image:buffer"]) == list(range(24))
