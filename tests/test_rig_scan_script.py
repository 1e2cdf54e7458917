"""benchmarks/rig_scan.py: argument parsing and a 20-frame smoke run (the full scan is a benchmark)."""
from __future__ import annotations

import math

import pytest
import torch

from slam.config import SLAMConfig, override
from slam.io import open_sequence
from slam.pipeline import evaluate_run, run_slam


def test_parse_args(load_script):
    rs = load_script("benchmarks/rig_scan.py")
    args = rs.parse_args([])
    assert args.tx == [0.025, 0.0, -0.015, -0.025, -0.04]
    assert args.max_frames is None and args.out is None and args.threads == 1
    args = rs.parse_args(["--tx", "+0.01", "-0.02", "--max-frames", "50"])
    assert args.tx == [0.01, -0.02] and args.max_frames == 50
    with pytest.raises(SystemExit):
        rs.parse_args(["--max-frames", "2"])  # too short for an ATE alignment
    with pytest.raises(SystemExit):
        rs.parse_args(["--tx", "nan"])


def test_smoke_20_frames(redkitchen_dir, tmp_path, capsys, load_script):
    rs = load_script("benchmarks/rig_scan.py")
    out = tmp_path / "scan.md"
    threads = torch.get_num_threads()
    try:  # one thread, as the benchmark runs (main sets it process-wide: restored for the other tests)
        rows = rs.main(["--data", str(redkitchen_dir.parent), "--tx", "0", "-0.025", "--max-frames", "20",
                        "--out", str(out)])
    finally:
        torch.set_num_threads(threads)
    assert [r["tx"] for r in rows] == [0.0, -0.025]
    max_rmse_mm = 1000.0 * SLAMConfig().odometry.registration.max_rmse
    for r in rows:
        # the first frame initialises, every other one registers once against its keyframe
        assert r["registrations"] == r["frames"] - 1 - r["lost"] and r["frames"] == 20
        assert 0.0 < r["rmse_mm"] <= max_rmse_mm  # success requires inlier RMSE <= max_rmse
        assert r["inliers"] >= SLAMConfig().odometry.registration.min_inliers
        for key in ("ate_se3", "ate_sim3", "scale", "seconds"):
            assert math.isfinite(r[key]), key
        assert r["ate_se3"] < 0.02  # 20 frames (0.67 s) of slow hand-held motion
        assert r["ate_sim3"] <= r["ate_se3"] + 1e-12  # Sim(3) has one more degree of freedom
    table = out.read_text()
    assert "| +0.000 |" in table and "| -0.025 |" in table
    assert capsys.readouterr().out.count("| -0.025 |") == 1

    # the same trajectory as the public pipeline's (depth-camera poses)
    cfg = SLAMConfig()
    cfg = override(cfg, {
        "loop.enabled": False,
        "odometry.features.rgb_intrinsics": rs.RGB_INTRINSICS,
        "odometry.features.rgb_from_depth_translation": (-0.025, 0.0, 0.0)})
    ref = evaluate_run(run_slam(open_sequence(redkitchen_dir), cfg, max_frames=20, progress=False))
    assert ref["ate_rmse"] == pytest.approx(rows[1]["ate_se3"], abs=1e-12)
    assert ref["num_keyframes"] == rows[1]["keyframes"]
