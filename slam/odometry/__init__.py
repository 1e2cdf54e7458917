"""Sparse RGB-D odometry: features, Kornia matching, 3D-3D RANSAC, registration and the tracking front end.

``register(feats_a, feats_b)`` is the two-frame registration (also the loop-closure verification);
``RGBDOdometry(config).track(frame)`` is the frame-to-keyframe front end.
"""
from slam.odometry.config import (
    FeatureConfig,
    MatchConfig,
    OdometryConfig,
    RansacConfig,
    RegistrationConfig,
)
from slam.odometry.features import FrameFeatures, extract_features
from slam.odometry.frontend import Keyframe, RGBDOdometry, TrackResult, TrackStatus
from slam.odometry.matching import match_features
from slam.odometry.registration import RegistrationResult, register

__all__ = [
    "FeatureConfig",
    "FrameFeatures",
    "Keyframe",
    "MatchConfig",
    "OdometryConfig",
    "RGBDOdometry",
    "RansacConfig",
    "RegistrationConfig",
    "RegistrationResult",
    "TrackResult",
    "TrackStatus",
    "extract_features",
    "match_features",
    "register",
]
