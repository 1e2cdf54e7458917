"""slam.options: the one mapping from run options to SLAMConfig (dataset rigs, overrides, checks), and the
API refusing settings that would give NaN poses."""
from __future__ import annotations

import argparse

import cv2
import numpy as np
import pytest
import torch

from slam.options import (
    KINECT_V1_RIG,
    REGISTERED,
    UsageError,
    add_run_arguments,
    check_config,
    check_device,
    config_from_args,
    dataset_rig,
    resolve_rig,
    run_options,
)


def _parse(*argv):
    p = argparse.ArgumentParser()
    add_run_arguments(p)
    return p.parse_args(list(argv))


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """The same 4 synthetic frames as a TUM folder and as a 7-Scenes folder."""
    from slam.io import open_sequence
    from slam.synthetic import generate_sequence

    root = tmp_path_factory.mktemp("seqs")
    tum = generate_sequence(root / "tum", num_frames=4, width=64, height=48)
    seq = open_sequence(tum)
    seven = root / "seven"
    seven.mkdir()
    for i in range(len(seq)):
        f = seq[i]
        cv2.imwrite(str(seven / f"frame-{i:06d}.color.png"), f.rgb[:, :, ::-1])
        cv2.imwrite(str(seven / f"frame-{i:06d}.depth.png"), np.round(f.depth * 1000).astype(np.uint16))
    return tum, seven


def test_dataset_rig_7scenes_is_the_kinect_tum_is_registered(folders):
    from slam.io import open_sequence

    tum, seven = folders
    assert dataset_rig(open_sequence(tum)) is REGISTERED
    assert dataset_rig(open_sequence(seven)) is KINECT_V1_RIG
    assert dataset_rig(open_sequence(seven)[0:2]) is KINECT_V1_RIG  # a view reads its parent's files
    cfg = config_from_args(_parse(), open_sequence(seven))
    f = cfg.odometry.features
    assert f.rgb_intrinsics == (525.0, 525.0, 320.0, 240.0) and f.rgb_from_depth_translation == (-0.025, 0.0, 0.0)
    assert config_from_args(_parse(), open_sequence(tum)).odometry.features.rgb_intrinsics is None


def test_flags_override_the_dataset_rig(folders):
    from slam.io import open_sequence

    tum, seven = map(open_sequence, folders)
    r = resolve_rig(_parse("--rgb-from-depth", "-0.03", "0", "0"), seven)  # baseline only: the K stays
    assert r.rgb_intrinsics == KINECT_V1_RIG.rgb_intrinsics and r.rgb_from_depth == (-0.03, 0.0, 0.0)
    r = resolve_rig(_parse("--rgb-intrinsics", "520", "521", "319", "241"), seven)  # K only: the baseline stays
    assert r.rgb_intrinsics == (520.0, 521.0, 319.0, 241.0) and r.rgb_from_depth == (-0.025, 0.0, 0.0)
    assert resolve_rig(_parse("--registered"), seven).registered
    r = resolve_rig(_parse("--rgb-intrinsics", "520", "521", "319", "241"), tum)  # a registered dataset
    assert r.rgb_from_depth == (0.0, 0.0, 0.0)
    with pytest.raises(UsageError, match="--rgb-intrinsics"):
        resolve_rig(_parse("--rgb-from-depth", "-0.025", "0", "0"), tum)
    with pytest.raises(UsageError, match="--registered"):
        resolve_rig(_parse("--registered", "--rgb-from-depth", "0", "0", "0"), seven)


@pytest.mark.parametrize("argv", [
    ["--rgb-from-depth", "inf", "0", "0"], ["--rgb-from-depth", "nan", "0", "0"],
    ["--rgb-intrinsics", "525", "525", "inf", "240"], ["--frame-step", "0"], ["--max-frames", "-3"],
    ["--map-voxel", "0"], ["--map-voxel", "inf"], ["--fusion", "bogus"], ["--backbone", "bogus"],
])
def test_non_finite_or_out_of_range_flags_are_usage_errors(argv, capsys):
    with pytest.raises(SystemExit) as e:
        _parse(*argv)
    assert e.value.code == 2
    assert argv[0] in capsys.readouterr().err


@pytest.mark.parametrize("values, match", [
    ("0 0 0 0", "focal lengths must be positive"), ("-525 525 320 240", "focal lengths must be positive"),
])
def test_impossible_intrinsics_are_refused_when_given(values, match):
    with pytest.raises(UsageError, match=match):
        config_from_args(_parse("--rgb-intrinsics", *values.split()))


def test_device_names_are_checked():
    assert check_device(None) is None and check_device("cpu") == "cpu"
    with pytest.raises(UsageError, match="not a torch device"):
        check_device("bogus")
    with pytest.raises(UsageError, match="not a torch device"):
        check_device("cuda:x")
    if not torch.cuda.is_available():
        with pytest.raises(UsageError, match="CUDA is not available"):
            check_device("cuda")
        with pytest.raises(UsageError, match="CUDA is not available"):
            config_from_args(_parse("--device", "cuda:0"))


def test_check_config_refuses_nan_anywhere_and_a_non_finite_rig():
    from slam.config import SLAMConfig

    check_config(SLAMConfig())  # the defaults pass
    cfg = SLAMConfig()
    cfg.loop.max_translation = float("inf")  # an infinite bound switches a check off: allowed
    check_config(cfg)
    cfg.odometry.registration.ransac.inlier_threshold = float("nan")
    with pytest.raises(UsageError, match="config.odometry.registration.ransac.inlier_threshold is NaN"):
        check_config(cfg)
    cfg = SLAMConfig()
    cfg.odometry.features.rgb_intrinsics = (525.0, 525.0, 320.0, 240.0)
    cfg.odometry.features.rgb_from_depth_translation = (float("inf"), 0.0, 0.0)
    with pytest.raises(UsageError, match="rgb_from_depth_translation must be finite"):
        check_config(cfg)


def test_run_slam_refuses_what_would_give_nan_poses(folders):
    """Through the API: an infinite baseline and zero intrinsics are refused, not returned as NaN poses."""
    from slam.config import SLAMConfig
    from slam.io import open_sequence
    from slam.pipeline import run_slam

    seq = open_sequence(folders[0])
    cfg = SLAMConfig()
    cfg.loop.enabled = False
    cfg.odometry.features.rgb_intrinsics = (50.0, 50.0, 32.0, 24.0)
    cfg.odometry.features.rgb_from_depth_translation = (float("inf"), 0.0, 0.0)
    with pytest.raises(ValueError, match="must be finite"):
        run_slam(seq, cfg, progress=False)
    cfg = SLAMConfig()
    cfg.loop.enabled = False
    seq.K = np.zeros((3, 3))
    with pytest.raises(ValueError, match="focal lengths must be positive"):
        run_slam(seq, cfg, progress=False)
    with pytest.raises(ValueError, match="frame_step"):
        run_slam(open_sequence(folders[0]), cfg, frame_step=0)


def test_run_options_defaults_and_overrides():
    ns = run_options(frame_step=3, backbone="efficientnet_lite0")
    assert (ns.frame_step, ns.backbone, ns.fusion, ns.registered) == (3, "efficientnet_lite0", "dam", False)
    with pytest.raises(UsageError, match="unknown run option 'step'"):
        run_options(step=3)


def test_one_list_of_fusion_modes():
    from attnloop.fusion import FUSION_MODES
    from slam.ablation import MODES

    assert MODES is FUSION_MODES
    p = argparse.ArgumentParser()
    add_run_arguments(p)
    assert tuple(next(a for a in p._actions if a.dest == "fusion").choices) == FUSION_MODES
