"""The command on input in the wrong units or that cannot be tracked: depth read at the wrong scale and
timestamps in nanoseconds are found when the folder is opened (exit code 2, one line naming the fix, or a
conversion with a notice); a run in which almost no frame tracks is a failure (exit code 1, one error line,
metrics.json alone, no trajectory)."""
from __future__ import annotations

import json
import os
import re

import cv2
import numpy as np
import pytest

from slam.cli import main

H, W = 48, 64
KITCHEN_FRAMES = 5


def _kitchen_as_tum(redkitchen_dir, root, n=KITCHEN_FRAMES):
    """7-Scenes frames (millimetre depth) written into TUM's layout (whose readers assume 5000 units per metre)."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb, depth = ["# color images\n"], ["# depth maps\n"]
    for k in range(n):
        t = 1000.0 + k / 30
        os.symlink(redkitchen_dir / f"frame-{k:06d}.color.jpg", root / "rgb" / f"{k}.jpg")
        os.symlink(redkitchen_dir / f"frame-{k:06d}.depth.png", root / "depth" / f"{k}.png")
        rgb.append(f"{t:.6f} rgb/{k}.jpg\n")
        depth.append(f"{t:.6f} depth/{k}.png\n")
    (root / "rgb.txt").write_text("".join(rgb))
    (root / "depth.txt").write_text("".join(depth))
    return root


def _one_error_line(err: str, prog: str = "attnloop-slam") -> str:
    lines = [ln for ln in err.splitlines() if ln.startswith(f"{prog}:") and "warning" not in ln]
    assert len(lines) == 1, err
    return lines[0]


def test_millimetre_depth_in_tum_layout_is_refused_naming_the_scale(redkitchen_dir, tmp_path, capsys):
    seq = _kitchen_as_tum(redkitchen_dir, tmp_path / "kitchen_tum")
    out = tmp_path / "out"
    assert main([str(seq), "--out", str(out), "--no-loop", "--quiet"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    # redkitchen's first frames: median 1878-1888 mm, i.e. 0.376-0.378 m read as 1/5000 m
    assert re.search(r"median of 0\.37\d m", line) and "--depth-scale 1000" in line and "millimetres" in line, line
    assert not out.exists()  # refused before anything is written
    # the scale it names opens the folder: depth at 1.88 m
    from slam.io import open_sequence

    assert abs(float(np.median(open_sequence(seq, depth_scale=1000)[0].depth[::4, ::4][
        open_sequence(seq, depth_scale=1000)[0].depth[::4, ::4] > 0])) - 1.878) < 0.011


def test_tum_depth_scale_on_7scenes_is_refused_naming_the_scale(redkitchen_dir, tmp_path, capsys):
    out = tmp_path / "out"
    assert main([str(redkitchen_dir), "--out", str(out), "--depth-scale", "5000", "--no-loop", "--quiet"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "5000 units per metre" in line and "--depth-scale 1000" in line, line
    assert not out.exists()


def test_no_depth_check_opens_a_scene_nearer_than_the_check_allows(redkitchen_dir, tmp_path, capsys):
    """A sequence whose median depth really is below 0.5 m (here: the kitchen at 1/5 scale) opens with the flag."""
    seq = _kitchen_as_tum(redkitchen_dir, tmp_path / "kitchen_tum")
    from slam.io import open_sequence
    from slam.io.sequence import DatasetError

    with pytest.raises(DatasetError, match="--no-depth-check"):
        open_sequence(seq)
    near = open_sequence(seq, check_units=False)[0].depth
    assert abs(float(np.median(near[near > 0])) - 1.878 / 5) < 0.003  # read at 5000 units per metre, as asked
    out = tmp_path / "out"
    assert main([str(seq), "--out", str(out), "--no-loop", "--no-map", "--quiet", "--max-frames", "5",
                 "--no-depth-check"]) == 0
    assert (out / "trajectory.txt").is_file()
    assert main(["--demo", "--out", str(tmp_path / "d"), "--no-depth-check"]) == 2  # the demo writes its own depth


def _write_frames(root, n=10, depth_dtype=np.uint16, truncate_rgb=False, swap_lists=False):
    """A TUM-layout folder of ``n`` textured frames at 1-2 m; optionally broken as users break them."""
    rng = np.random.default_rng(0)
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb, depth = [], []
    for k in range(n):
        t = 1.0 + k / 30
        img = rng.integers(0, 256, (H, W, 3), np.uint8)
        ok, enc = cv2.imencode(".jpg", img)
        data = enc.tobytes()
        (root / "rgb" / f"{k}.jpg").write_bytes(data[:len(data) // 2] if truncate_rgb else data)
        d = np.full((H, W), 7500, np.uint16)  # 1.5 m at 5000 units per metre
        cv2.imwrite(str(root / "depth" / f"{k}.png"), (d // 256).astype(np.uint8) if depth_dtype == np.uint8 else d)
        rgb.append(f"{t:.6f} rgb/{k}.jpg\n")
        depth.append(f"{t:.6f} depth/{k}.png\n")
    if swap_lists:
        rgb, depth = depth, rgb
    (root / "rgb.txt").write_text("".join(rgb))
    (root / "depth.txt").write_text("".join(depth))
    return root


@pytest.mark.parametrize("broken, cause", [
    (dict(depth_dtype=np.uint8), "depth image must be 16-bit"),
    (dict(swap_lists=True), "colour image must be 8-bit"),
    (dict(truncate_rgb=True), "not a decodable image"),
])
def test_a_run_where_no_frame_tracks_fails_with_one_line_and_no_trajectory(broken, cause, tmp_path, capsys):
    seq = _write_frames(tmp_path / "seq", **broken)
    out = tmp_path / "out"
    out.mkdir()
    (out / "trajectory.txt").write_text("0 0 0 0 0 0 0 1\n")  # an earlier run's: must not pass for this one's
    assert main([str(seq), "--out", str(out), "--no-loop", "--no-map", "--quiet"]) == 1
    err = capsys.readouterr().err
    line = _one_error_line(err)
    assert "0 of 10 frames tracked (0 lost, 10 unreadable)" in line and cause in line, line
    assert "min_tracked_fraction" in line and "metrics.json" in line
    assert len(err.splitlines()) <= 4, err  # three frames listed, then counted: not one line per frame
    assert sorted(p.name for p in out.iterdir()) == ["config.toml", "metrics.json"]  # the settings, no result
    m = json.loads((out / "metrics.json").read_text())
    assert (m["status"], m["num_tracked"], m["num_skipped"], m["num_frames"]) == ("failed", 0, 10, 10)
    assert cause in m["failure"]


def test_min_tracked_fraction_is_checked():
    from slam.config import SLAMConfig

    with pytest.raises(ValueError, match="min_tracked_fraction must be"):
        SLAMConfig(min_tracked_fraction=1.5)
    with pytest.raises(ValueError, match="min_tracked_fraction must be"):
        SLAMConfig(min_tracked_fraction=float("nan"))


# --- --intrinsics: a registered camera's, on any folder ------------------------------------------------------


def _open_with(argv, folder):
    from slam.cli import build_parser
    from slam.options import given_settings, resolve_settings

    args = build_parser().parse_args([str(folder), "--out", "o", *argv])
    spec = resolve_settings(given_settings(args), None, args.sequence)
    return spec.sequence, spec.config


def test_intrinsics_on_7scenes_replace_its_camera_and_its_rig(redkitchen_dir):
    seq, cfg = _open_with(["--intrinsics", "580", "581", "321", "241"], redkitchen_dir)
    np.testing.assert_array_equal(seq.K, [[580, 0, 321], [0, 581, 241], [0, 0, 1]])
    assert cfg.odometry.features.rgb_intrinsics is None  # registered: the Kinect v1 rig is not applied
    assert cfg.odometry.features.rgb_from_depth_translation == (0.0, 0.0, 0.0)
    # with --rgb-intrinsics they are the depth camera's, and the rig is the flags'
    seq, cfg = _open_with(["--intrinsics", "580", "581", "321", "241", "--rgb-intrinsics", "525", "525", "320", "240",
                           "--rgb-from-depth", "-0.02", "0", "0"], redkitchen_dir)
    assert seq.K[0, 0] == 580 and cfg.odometry.features.rgb_intrinsics == (525.0, 525.0, 320.0, 240.0)
    assert cfg.odometry.features.rgb_from_depth_translation == (-0.02, 0.0, 0.0)


def test_intrinsics_on_tum_replace_calibration_txt(tmp_path):
    seq_dir = _write_frames(tmp_path / "seq", n=2)
    (seq_dir / "calibration.txt").write_text("# fx fy cx cy\n500 500 32 24\n")
    seq, _ = _open_with([], seq_dir)
    assert seq.K[0, 0] == 500 and seq.camera_name == "calibration.txt"
    seq, cfg = _open_with(["--intrinsics", "60", "61", "31.5", "23.5"], seq_dir)
    np.testing.assert_array_equal(seq.K, [[60, 0, 31.5], [0, 61, 23.5], [0, 0, 1]])
    assert cfg.odometry.features.rgb_intrinsics is None


@pytest.mark.parametrize("argv, expected", [
    (["--intrinsics", "0", "500", "320", "240"],
     "--intrinsics (0.0, 500.0, 320.0, 240.0): run: RunOptions.intrinsics: focal lengths must be positive"),
    (["--intrinsics", "500", "500", "320", "240", "--camera", "fr1"], "--intrinsics and --camera"),
])
def test_intrinsics_that_cannot_be_used_are_refused(argv, expected, tmp_path, capsys):
    seq = _write_frames(tmp_path / "seq", n=2)
    assert main([str(seq), "--out", str(tmp_path / "out"), "--no-loop", *argv]) == 2
    assert expected in _one_error_line(capsys.readouterr().err)
    assert not (tmp_path / "out").exists()


def test_camera_on_7scenes_names_a_flag_that_exists(redkitchen_dir, tmp_path, capsys):
    assert main([str(redkitchen_dir), "--out", str(tmp_path / "out"), "--camera", "fr1", "--no-loop"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "--intrinsics FX FY CX CY" in line, line
    seq, _ = _open_with(["--intrinsics", "517.3", "516.5", "318.6", "255.3"], redkitchen_dir)  # what it says works
    assert seq.K[0, 0] == 517.3


def test_a_demo_too_fast_to_track_fails_with_the_reason(tmp_path, capsys):
    """12 frames for the room's whole loop: every frame after the first is lost (too few matches)."""
    out = tmp_path / "out"
    assert main(["--demo", "--demo-frames", "12", "--demo-size", "160", "120", "--no-loop", "--quiet",
                 "--out", str(out)]) == 1
    line = _one_error_line(capsys.readouterr().err)
    assert "1 of 12 frames tracked (11 lost, 0 unreadable)" in line and "frame 1 lost: registration failed" in line
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "failed" and m["ate_unavailable"].startswith("no frame was tracked")
    assert not (out / "trajectory.txt").exists() and (out / "demo_sequence" / "rgb.txt").is_file()


# --- timestamps in nanoseconds --------------------------------------------------------------------------------


def _restamp(src, dst, per_second: int):
    """A copy of the TUM folder ``src`` whose list and ground-truth stamps are in 1/per_second s (integers)."""
    import shutil

    shutil.copytree(src, dst, symlinks=True)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        lines = []
        for line in (src / name).read_text().splitlines():
            if line.strip() and not line.startswith("#"):
                first, rest = line.split(maxsplit=1)
                line = f"{round(float(first) * per_second)} {rest}"
            lines.append(line)
        (dst / name).write_text("\n".join(lines) + "\n")
    return dst


@pytest.mark.slow
def test_nanosecond_stamps_are_converted_with_a_notice_and_close_the_same_loops(tmp_path, caplog):
    """The room demo (300 frames at 160 x 120) with its stamps in nanoseconds: one notice, then the run of the
    seconds version to the bit: its loops (the 3 s exclusion window applies again), poses and ATE."""
    from slam.synthetic.demo import generate_demo

    seconds = generate_demo(tmp_path / "seconds", width=160, height=120)
    nanos = _restamp(seconds, tmp_path / "nanos", 10 ** 9)
    assert (nanos / "rgb.txt").read_text().splitlines()[3].startswith("1700000000000000000 ")
    runs = {}
    for name, seq in (("s", seconds), ("ns", nanos)):
        out = tmp_path / f"out_{name}"
        assert main([str(seq), "--out", str(out), "--no-map", "--quiet"]) == 0
        runs[name] = out
    notices = [r.getMessage() for r in caplog.records if "nanoseconds" in r.getMessage()]
    assert len(notices) == 1 and "rgb.txt in nanoseconds (30 Hz)" in notices[0], notices
    assert "groundtruth.txt in nanoseconds" in notices[0] and "converted to seconds" in notices[0]
    loops = (runs["s"] / "loops.txt").read_text()
    assert loops.count("\n") > 10 and (runs["ns"] / "loops.txt").read_text() == loops
    np.testing.assert_allclose(np.loadtxt(runs["ns"] / "trajectory.txt"), np.loadtxt(runs["s"] / "trajectory.txt"),
                               rtol=0, atol=1e-6)
    m_s, m_ns = (json.loads((runs[k] / "metrics.json").read_text()) for k in ("s", "ns"))
    assert m_ns["ate_rmse"] == m_s["ate_rmse"] and m_ns["num_loops"] == m_s["num_loops"] == loops.count("\n") - 1
