"""slam.options: the one mapping from run settings (flags, a library caller's keys, a config file) to
SLAMConfig and RunOptions: dataset rigs, overrides, checks; and the API refusing settings that would give
NaN poses."""
from __future__ import annotations

import argparse
import math

import cv2
import numpy as np
import pytest
import torch

from slam.config import REGISTERED, ConfigError, SLAMConfig, override
from slam.options import (
    KINECT_V1_RIG,
    OPTIONS,
    RunOptions,
    UsageError,
    add_run_arguments,
    check_device,
    dataset_rig,
    given_settings,
    resolve_settings,
)


def _parse(*argv):
    p = argparse.ArgumentParser()
    add_run_arguments(p)
    return p.parse_args(list(argv))


def _config(*argv, sequence=None):
    """The config the command builds from ``argv`` (and the dataset's rig of ``sequence``)."""
    return resolve_settings(given_settings(_parse(*argv)), sequence=sequence).config


def _rig(cfg):
    f = cfg.odometry.features
    return f.rgb_intrinsics, f.rgb_from_depth_translation


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
    assert _rig(_config(sequence=open_sequence(seven))) == ((525.0, 525.0, 320.0, 240.0), (-0.025, 0.0, 0.0))
    assert _rig(_config(sequence=seven)) == _rig(_config(sequence=open_sequence(seven)))  # a folder is opened
    assert _rig(_config(sequence=open_sequence(tum))) == (None, (0.0, 0.0, 0.0))


def test_flags_override_the_dataset_rig(folders):
    from slam.io import open_sequence

    tum, seven = map(open_sequence, folders)
    # baseline only: the K stays; K only: the baseline stays
    assert _rig(_config("--rgb-from-depth", "-0.03", "0", "0", sequence=seven)) == (
        KINECT_V1_RIG.rgb_intrinsics, (-0.03, 0.0, 0.0))
    assert _rig(_config("--rgb-intrinsics", "520", "521", "319", "241", sequence=seven)) == (
        (520.0, 521.0, 319.0, 241.0), (-0.025, 0.0, 0.0))
    assert _rig(_config("--registered", sequence=seven)) == (None, (0.0, 0.0, 0.0))
    assert _rig(_config("--rgb-intrinsics", "520", "521", "319", "241", sequence=tum)) == (  # a registered dataset
        (520.0, 521.0, 319.0, 241.0), (0.0, 0.0, 0.0))
    with pytest.raises(UsageError, match="--rgb-intrinsics"):
        _config("--rgb-from-depth", "-0.025", "0", "0", sequence=tum)
    with pytest.raises(UsageError, match="--registered"):
        _config("--registered", "--rgb-from-depth", "0", "0", "0", sequence=seven)


def test_a_config_files_rig_is_kept_over_the_datasets(folders, tmp_path):
    # a run's config.toml holds the rig it ran with: read back on the same 7-Scenes folder it must stay
    from slam.io import open_sequence

    seven = open_sequence(folders[1])
    spec = resolve_settings({"rig.registered": True}, sequence=seven)
    spec.save(tmp_path / "config.toml")
    again = resolve_settings({}, tmp_path / "config.toml", seven)
    assert _rig(again.config) == (None, (0.0, 0.0, 0.0)) and again.config == spec.config


@pytest.mark.parametrize("argv", [
    ["--rgb-from-depth", "inf", "0", "0"], ["--rgb-from-depth", "nan", "0", "0"],
    ["--rgb-intrinsics", "525", "525", "inf", "240"], ["--frame-step", "0"], ["--max-frames", "-3"],
    ["--map-voxel", "0"], ["--map-voxel", "inf"], ["--fusion", "bogus"], ["--backbone", "bogus"],
    ["--preset", "bogus"],
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
        _config("--rgb-intrinsics", *values.split())


def test_device_names_are_checked():
    assert check_device(None, "d") is None and check_device("cpu", "d") == "cpu"
    with pytest.raises(ValueError, match="not a torch device"):
        check_device("bogus", "d")
    with pytest.raises(ValueError, match="not a torch device"):
        check_device("cuda:x", "d")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            check_device("cuda", "d")


def test_configs_refuse_nan_anywhere_and_a_non_finite_rig():
    cfg = override(SLAMConfig(), {"loop.max_translation": math.inf})  # an infinite bound switches a check off
    assert cfg.loop.max_translation == math.inf
    with pytest.raises(ConfigError, match=r"odometry\.registration\.ransac: RansacConfig\.inlier_threshold"):
        override(SLAMConfig(), {"odometry.registration.ransac.inlier_threshold": math.nan})
    with pytest.raises(ConfigError, match="rgb_from_depth_translation must be 3 finite numbers"):
        override(SLAMConfig(), {"odometry.features.rgb_intrinsics": (525.0, 525.0, 320.0, 240.0),
                                "odometry.features.rgb_from_depth_translation": (math.inf, 0.0, 0.0)})


def test_run_slam_refuses_what_would_give_nan_poses(folders):
    """Through the API: zero intrinsics and a bad frame step are refused, not returned as NaN poses."""
    from slam.io import open_sequence
    from slam.pipeline import run_slam

    seq = open_sequence(folders[0])
    cfg = override(SLAMConfig(), {"loop.enabled": False})
    seq.K = np.zeros((3, 3))
    with pytest.raises(ValueError, match="focal lengths must be positive"):
        run_slam(seq, cfg, progress=False)
    with pytest.raises(ValueError, match="frame_step"):
        run_slam(open_sequence(folders[0]), cfg, frame_step=0)
    with pytest.raises(TypeError, match="SLAMConfig"):
        run_slam(open_sequence(folders[0]), {"loop": {"enabled": False}})


def test_a_library_callers_keys_are_the_flags_keys():
    flags = ("--no-loop", "--frame-step", "3", "--threads", "2", "--map-voxel", "0.05", "--camera", "fr2")
    typed = given_settings(_parse(*flags))
    assert typed == {"loop.enabled": False, "run.frame_step": 3, "threads": 2, "map.voxel_size": 0.05,
                     "run.camera": "fr2"}
    spec = resolve_settings(typed)
    assert spec.run == RunOptions(frame_step=3, camera="fr2")
    assert spec.config == override(SLAMConfig(), {"loop.enabled": False, "threads": 2, "map.voxel_size": 0.05})
    with pytest.raises(ConfigError, match="unknown key 'loop.fusoin'; LoopClosureConfig has enabled, descriptor"):
        resolve_settings({"loop.fusoin": "dam"})
    with pytest.raises(ConfigError, match="unknown key 'run.step'; RunOptions has frame_step"):
        resolve_settings({"run.step": 3})
    assert all(opt.key.startswith(("run.", "rig.")) or _has_field(opt.key) for opt in OPTIONS)


def _has_field(key: str) -> bool:
    obj = SLAMConfig()
    for part in key.split("."):
        if not hasattr(obj, part):
            return False
        obj = getattr(obj, part)
    return True


def test_one_list_of_fusion_modes():
    from attnloop.fusion import FUSION_MODES
    from slam.ablation import COLUMNS

    assert tuple(COLUMNS["default"]) == FUSION_MODES
    p = argparse.ArgumentParser()
    add_run_arguments(p)
    assert tuple(next(a for a in p._actions if a.dest == "loop.descriptor.fusion").choices) == FUSION_MODES
