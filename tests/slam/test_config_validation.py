"""Config validation: a bad setting is refused when the config is built, with a ValueError naming the field.

Before, a typo in a name or an out-of-range number built fine and surfaced late or never: an unknown
detector made every frame "lost" (the front end reads a config error as a bad frame), a bad back-end
kernel failed only when the first loop was accepted, ``max_candidates=0`` verified nothing.
"""
import dataclasses
import math

import pytest

from attnloop.index import LoopDetectorConfig
from attnloop.threshold import ThresholdConfig
from slam.backend import OPTIMIZER_METHODS
from slam.config import BackendConfig, LoopClosureConfig, SLAMConfig, override
from slam.loop.consistency import ConsistencyConfig
from slam.mapping import MapConfig
from slam.odometry.config import (
    DETECTORS,
    MATCH_METHODS,
    FeatureConfig,
    MatchConfig,
    OdometryConfig,
    RansacConfig,
    RegistrationConfig,
)


def test_the_defaults_build_and_survive_replace():
    cfg = SLAMConfig()
    for obj in (cfg, cfg.odometry, cfg.odometry.features, cfg.odometry.registration, cfg.odometry.registration.ransac,
                cfg.odometry.registration.matching, cfg.loop, cfg.loop.registration, cfg.backend):
        assert dataclasses.replace(obj) == obj  # replace re-runs __post_init__
    # every listed choice is accepted
    for d in DETECTORS:
        FeatureConfig(detector=d)
    for m in MATCH_METHODS:
        MatchConfig(method=m)
    for m in OPTIMIZER_METHODS + ("GN",):
        BackendConfig(method=m)
    for k in ("dcs", "DCS", "none", "huber", "cauchy", "tukey", "geman_mcclure", None):
        BackendConfig(loop_kernel=k)


# infinite bounds switch a check off and stay allowed
@pytest.mark.parametrize("cls, kwargs", [
    (MatchConfig, dict(max_hamming=math.inf, ratio=1.0, guided_radius_px=0.0)),
    (RegistrationConfig, dict(max_rmse=math.inf)),
    (OdometryConfig, dict(keyframe_translation=math.inf, keyframe_rotation_deg=0.0)),
    (FeatureConfig, dict(max_depth=math.inf, rgb_intrinsics=(525.0, 525.0, 320.0, 240.0))),
    (RansacConfig, dict(confidence=1.0, min_iterations=1024, seed=-3)),
    (LoopClosureConfig, dict(max_translation=math.inf, max_candidates=1)),
])
def test_edge_values_are_accepted(cls, kwargs):
    cls(**kwargs)


@pytest.mark.parametrize("cls, kwargs, field", [
    # FeatureConfig
    (FeatureConfig, dict(detector="ORB"), r"FeatureConfig\.detector must be one of 'orb', 'sift', got 'ORB'"),
    (FeatureConfig, dict(image_scale=-1), r"FeatureConfig\.image_scale must be > 0"),
    (FeatureConfig, dict(image_scale=math.nan), r"FeatureConfig\.image_scale"),
    (FeatureConfig, dict(detect_features=0), r"FeatureConfig\.detect_features"),
    (FeatureConfig, dict(max_features=-5), r"FeatureConfig\.max_features must be an integer >= 1, got -5"),
    (FeatureConfig, dict(max_features=10.5), r"FeatureConfig\.max_features"),
    (FeatureConfig, dict(grid_rows=0), r"FeatureConfig\.grid_rows"),
    (FeatureConfig, dict(grid_cols=0), r"FeatureConfig\.grid_cols"),
    (FeatureConfig, dict(orb_scale_factor=1.0), r"FeatureConfig\.orb_scale_factor"),
    (FeatureConfig, dict(orb_levels=0), r"FeatureConfig\.orb_levels"),
    (FeatureConfig, dict(fast_threshold=-1), r"FeatureConfig\.fast_threshold"),
    (FeatureConfig, dict(min_depth=-0.1), r"FeatureConfig\.min_depth"),
    (FeatureConfig, dict(min_depth=5.0), r"FeatureConfig\.max_depth \(4\.0\) must be > FeatureConfig\.min_depth"),
    (FeatureConfig, dict(depth_window_radius=-1), r"FeatureConfig\.depth_window_radius"),
    (FeatureConfig, dict(max_depth_jump=0.0), r"FeatureConfig\.max_depth_jump"),
    (FeatureConfig, dict(keypoint_sigma_px=0.0), r"FeatureConfig\.keypoint_sigma_px"),
    (FeatureConfig, dict(rgb_intrinsics=(525.0, 525.0, 320.0)), r"FeatureConfig\.rgb_intrinsics"),
    (FeatureConfig, dict(rgb_from_depth_translation=(math.inf, 0.0, 0.0)), r"FeatureConfig\.rgb_from_depth"),
    # MatchConfig
    (MatchConfig, dict(method="nn"), r"MatchConfig\.method must be one of 'smnn', 'snn', 'mnn'"),
    (MatchConfig, dict(ratio=-1), r"MatchConfig\.ratio must be in \(0, 1\], got -1"),
    (MatchConfig, dict(ratio=1.5), r"MatchConfig\.ratio"),
    (MatchConfig, dict(max_hamming=0), r"MatchConfig\.max_hamming"),
    (MatchConfig, dict(max_l2=-1.0), r"MatchConfig\.max_l2"),
    (MatchConfig, dict(guided_radius_px=-1.0), r"MatchConfig\.guided_radius_px"),
    # RansacConfig
    (RansacConfig, dict(confidence=2), r"RansacConfig\.confidence must be in \(0, 1\], got 2"),
    (RansacConfig, dict(confidence=0), r"RansacConfig\.confidence"),
    (RansacConfig, dict(max_iterations=0), r"RansacConfig\.max_iterations must be an integer >= 1"),
    (RansacConfig, dict(min_iterations=2048), r"RansacConfig\.min_iterations must be an integer in \[0, 1024\]"),
    (RansacConfig, dict(batch_size=0), r"RansacConfig\.batch_size"),
    (RansacConfig, dict(inlier_threshold=0.0), r"RansacConfig\.inlier_threshold"),
    (RansacConfig, dict(inlier_sigmas=-1.0), r"RansacConfig\.inlier_sigmas"),
    (RansacConfig, dict(min_sample_area=-1.0), r"RansacConfig\.min_sample_area"),
    (RansacConfig, dict(min_inliers=2), r"RansacConfig\.min_inliers"),
    (RansacConfig, dict(min_spread=-1.0), r"RansacConfig\.min_spread"),
    (RansacConfig, dict(refine_iterations=-1), r"RansacConfig\.refine_iterations"),
    (RansacConfig, dict(huber_delta=0.0), r"RansacConfig\.huber_delta"),
    (RansacConfig, dict(seed=0.5), r"RansacConfig\.seed"),
    # RegistrationConfig
    (RegistrationConfig, dict(min_matches=-1), r"RegistrationConfig\.min_matches"),
    (RegistrationConfig, dict(min_inliers=-1), r"RegistrationConfig\.min_inliers"),
    (RegistrationConfig, dict(max_rmse=0.0), r"RegistrationConfig\.max_rmse"),
    (RegistrationConfig, dict(depth_sigma_a=0.0), r"RegistrationConfig\.depth_sigma_a"),
    (RegistrationConfig, dict(depth_sigma_b=-1.0), r"RegistrationConfig\.depth_sigma_b"),
    (RegistrationConfig, dict(depth_sigma_c=math.inf), r"RegistrationConfig\.depth_sigma_c"),
    # OdometryConfig
    (OdometryConfig, dict(keyframe_rgb_scale=0.0), r"OdometryConfig\.keyframe_rgb_scale must be in \(0, 1\]"),
    (OdometryConfig, dict(keyframe_rgb_scale=-1.0), r"OdometryConfig\.keyframe_rgb_scale"),
    (OdometryConfig, dict(min_valid_points=-1), r"OdometryConfig\.min_valid_points"),
    (OdometryConfig, dict(keyframe_translation=-0.1), r"OdometryConfig\.keyframe_translation"),
    (OdometryConfig, dict(keyframe_rotation_deg=math.nan), r"OdometryConfig\.keyframe_rotation_deg"),
    (OdometryConfig, dict(keyframe_min_inliers=-1), r"OdometryConfig\.keyframe_min_inliers"),
    (OdometryConfig, dict(keyframe_min_inlier_ratio=1.5), r"OdometryConfig\.keyframe_min_inlier_ratio"),
    (OdometryConfig, dict(max_lost_frames=0), r"OdometryConfig\.max_lost_frames"),
    (OdometryConfig, dict(weak_edge_information=0.0), r"OdometryConfig\.weak_edge_information"),
    # LoopClosureConfig
    (LoopClosureConfig, dict(max_candidates=0), r"LoopClosureConfig\.max_candidates must be an integer >= 1"),
    (LoopClosureConfig, dict(recover_after_loss=1), r"LoopClosureConfig\.recover_after_loss must be True or False"),
    (LoopClosureConfig, dict(release_revisits="no"), r"LoopClosureConfig\.release_revisits must be True or False"),
    (LoopClosureConfig, dict(max_candidates=-1), r"LoopClosureConfig\.max_candidates"),
    (LoopClosureConfig, dict(max_candidates=6),
     r"LoopClosureConfig\.max_candidates \(6\) must be <= LoopClosureConfig\.detector\.top_k \(5\)"),
    (LoopClosureConfig, dict(min_inliers=-1), r"LoopClosureConfig\.min_inliers"),
    (LoopClosureConfig, dict(min_inlier_ratio=2.0), r"LoopClosureConfig\.min_inlier_ratio"),
    (LoopClosureConfig, dict(max_translation=0.0), r"LoopClosureConfig\.max_translation"),
    (LoopClosureConfig, dict(max_rotation_deg=-1.0), r"LoopClosureConfig\.max_rotation_deg"),
    (LoopClosureConfig, dict(information_scale=0.0), r"LoopClosureConfig\.information_scale"),
    (LoopClosureConfig, dict(threshold_by_backbone={"x": 0.85}), r"LoopClosureConfig\.threshold_by_backbone\['x'\]"),
    (LoopClosureConfig, dict(threshold_by_backbone={"x": ThresholdConfig(min_samples=10_000)}),
     r"LoopClosureConfig\.threshold_by_backbone\['x'\]: LoopDetectorConfig\.threshold_samples \(4096\) must be >= "
     r"threshold\.min_samples \(10000\)"),
    # ConsistencyConfig (checked by itself, so also inside LoopClosureConfig)
    (ConsistencyConfig, dict(min_group=0), r"ConsistencyConfig\.min_group must be an integer >= 1, got 0"),
    (ConsistencyConfig, dict(max_exact=-1), r"ConsistencyConfig\.max_exact must be an integer >= 0, got -1"),
    (ConsistencyConfig, dict(min_support=1.5), r"ConsistencyConfig\.min_support"),
    # BackendConfig
    (BackendConfig, dict(method="newton"), r"BackendConfig\.method must be one of 'lm', 'gn', got 'newton'"),
    (BackendConfig, dict(kernel="cauhy"), r"BackendConfig\.kernel must be a kernel name .* got 'cauhy'"),
    (BackendConfig, dict(loop_kernel="bogus"), r"BackendConfig\.loop_kernel: unknown loop kernel 'bogus'"),
    (BackendConfig, dict(loop_kernel=3), r"BackendConfig\.loop_kernel"),
    (BackendConfig, dict(kernel_width=-1.0), r"BackendConfig\.kernel_width must be > 0"),
    (BackendConfig, dict(loop_kernel_width=0.0), r"BackendConfig\.loop_kernel_width"),
    (BackendConfig, dict(max_iterations=0), r"BackendConfig\.max_iterations must be an integer >= 1, got 0"),
    (BackendConfig, dict(online_max_iterations=0), r"BackendConfig\.online_max_iterations"),
    (BackendConfig, dict(odometry_information_scale=0.0), r"BackendConfig\.odometry_information_scale"),
    (BackendConfig, dict(switch_off_weight=1.5), r"BackendConfig\.switch_off_weight"),
    # SLAMConfig: the map's depth range against the odometry's
    (SLAMConfig, dict(map=MapConfig(min_depth=5.0)),
     r"SLAMConfig\.map: the depth range must have max_depth > min_depth, got min_depth 5\.0, max_depth 4\.0"),
    # MapConfig on its own
    (MapConfig, dict(max_depth=-1.0), r"MapConfig\.max_depth must be None or a number >= 0, got -1\.0"),
    (MapConfig, dict(min_depth=3.0, max_depth=2.0), r"MapConfig: max_depth \(2\.0\) must be > min_depth \(3\.0\)"),
])
def test_a_bad_setting_is_refused_naming_the_field(cls, kwargs, field):
    with pytest.raises(ValueError, match=field):
        cls(**kwargs)
    with pytest.raises(ValueError, match=field):  # the same through dataclasses.replace
        dataclasses.replace(cls(), **kwargs)


def test_nested_configs_are_checked_when_built():
    with pytest.raises(ValueError, match=r"FeatureConfig\.detector"):
        OdometryConfig(features=FeatureConfig(detector="ORB"))
    with pytest.raises(ValueError, match=r"RansacConfig\.confidence"):
        LoopClosureConfig(registration=RegistrationConfig(ransac=RansacConfig(confidence=2)))
    # a smaller top_k with max_candidates to match is fine
    LoopClosureConfig(detector=LoopDetectorConfig(top_k=3), max_candidates=3)


def _configs(obj, path="config"):
    yield path, obj
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            yield from _configs(value, f"{path}.{f.name}")


def test_every_config_is_frozen_and_changed_by_replace():
    # a field set after the config was built would skip its checks (every frame lost on detector "ORB",
    # no loop ever verified at max_candidates 0): no config can be changed in place
    cfg = SLAMConfig()
    for path, obj in _configs(cfg):
        name = dataclasses.fields(obj)[0].name
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(obj, name, getattr(obj, name))
    assert len(list(_configs(cfg))) >= 15  # every nested config was visited
    with pytest.raises(ValueError, match=r"FeatureConfig\.detector must be one of"):
        override(cfg, {"odometry.features.detector": "ORB"})
    with pytest.raises(ValueError, match=r"^loop: LoopClosureConfig\.max_candidates must be an integer >= 1"):
        override(cfg, {"loop.max_candidates": 0})
    changed = override(cfg, {"odometry.features.detector": "sift", "loop.max_candidates": 3})
    assert (changed.odometry.features.detector, changed.loop.max_candidates) == ("sift", 3)
    assert (cfg.odometry.features.detector, cfg.loop.max_candidates) == ("orb", 5)  # the original unchanged
    assert changed.odometry.registration is cfg.odometry.registration  # what is not changed is shared


@pytest.mark.parametrize("kwargs, match", [
    (dict(backbone="resnet50"), r"DescriptorConfig\.backbone must be one of 'auto', 'vgg16', 'efficientnet_lite0'"),
    (dict(fusion="DAM"), r"DescriptorConfig\.fusion must be one of 'none', 'dam', 'eam', 'gaf', 'ega', got 'DAM'"),
    (dict(num_rnn=-1), r"DescriptorConfig\.num_rnn must be an integer >= 0"),
    (dict(seed=1.5), r"DescriptorConfig\.seed must be an integer >= 0"),
    (dict(pretrained="yes"), r"DescriptorConfig\.pretrained must be True or False"),
])
def test_descriptor_config_refuses_what_the_descriptor_would_refuse_later(kwargs, match):
    from slam.config import DescriptorConfig

    DescriptorConfig()  # the defaults build
    with pytest.raises(ValueError, match=match):
        DescriptorConfig(**kwargs)
