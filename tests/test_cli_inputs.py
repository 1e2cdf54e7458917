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
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json"]
    m = json.loads((out / "metrics.json").read_text())
    assert (m["status"], m["num_tracked"], m["num_skipped"], m["num_frames"]) == ("failed", 0, 10, 10)
    assert cause in m["failure"]


def test_min_tracked_fraction_is_checked():
    from slam.config import SLAMConfig

    with pytest.raises(ValueError, match="min_tracked_fraction must be in"):
        SLAMConfig(min_tracked_fraction=1.5)
    with pytest.raises(ValueError, match="min_tracked_fraction must be in"):
        SLAMConfig(min_tracked_fraction=float("nan"))
