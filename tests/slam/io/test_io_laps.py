"""LapSequence: a sequence played as laps, forward and backward, with increasing timestamps; --laps."""
from __future__ import annotations


import numpy as np
import pytest

from slam.io.laps import LapSequence, lap_indices
from slam.options import RunOptions, apply_laps, resolve_settings
from slam.synthetic import SyntheticSequence


@pytest.fixture(scope="module")
def source():
    return SyntheticSequence("loop", num_frames=5, width=32, height=24)


def test_laps_alternate_and_keep_time_moving(source):
    laps = LapSequence(source, 3)
    assert len(laps) == 15
    assert laps.source_indices.tolist() == [0, 1, 2, 3, 4, 4, 3, 2, 1, 0, 0, 1, 2, 3, 4]
    src = source.timestamps
    dt = float(np.median(np.diff(src)))
    want = [src[0]]
    for prev, cur in zip(laps.source_indices[:-1], laps.source_indices[1:]):
        want.append(want[-1] + (abs(src[cur] - src[prev]) if cur != prev else dt))
    assert np.allclose(laps.timestamps, want) and np.all(np.diff(laps.timestamps) > 0)
    # each frame is its source frame, re-numbered and re-stamped; ground truth is the source's
    f, g = laps[6], source[3]
    assert f.index == 6 and f.timestamp == pytest.approx(laps.timestamps[6])
    assert np.array_equal(f.rgb, g.rgb) and np.array_equal(f.depth, g.depth) and np.allclose(f.pose_gt, g.pose_gt)
    gt = laps.groundtruth
    assert len(gt) == 15 and np.allclose(gt.poses[9].numpy(), source.groundtruth_pose(0))
    # a view of the laps (as run_slam takes with a frame step) keeps the source frames' ground truth
    view = laps[0:15:4]
    assert np.allclose(view.groundtruth.poses.numpy(), laps.groundtruth.poses.numpy()[0:15:4])


def test_lap_arguments_are_checked(source):
    with pytest.raises(ValueError, match="laps"):
        lap_indices(5, 0)
    with pytest.raises(ValueError, match="at least one frame"):
        lap_indices(0, 2)
    with pytest.raises(TypeError, match="RGBDSequence"):
        LapSequence([1, 2, 3], 2)


def test_laps_option(source):
    assert apply_laps(RunOptions(), source) is source
    laps = apply_laps(RunOptions(laps=2), source)
    assert isinstance(laps, LapSequence) and len(laps) == 10
    assert len(resolve_settings({"run.laps": 2}, None, source).sequence) == 10  # every entry point gets the laps
    with pytest.raises(ValueError, match="RunOptions.laps must be an integer >= 1"):
        RunOptions(laps=0)


def test_cli_runs_the_laps(tmp_path):
    import json

    from slam.cli import main

    out = tmp_path / "run"
    assert main(["--demo", "--demo-frames", "24", "--demo-size", "160", "120", "--laps", "2", "--no-loop",
                 "--no-map", "--quiet", "--out", str(out)]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["num_frames"] == 48 and metrics["status"] == "ok"
    stamps = np.loadtxt(out / "trajectory.txt")[:, 0]
    assert stamps.size == 48 and np.all(np.diff(stamps) > 0)
