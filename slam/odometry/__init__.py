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
from slam.odometry.features import FrameFeatures, bucket_keypoints, extract_features
from slam.odometry.frontend import Keyframe, KeyframeEdge, RGBDOdometry, TrackResult, TrackStatus
from slam.odometry.geometry import (
    backproject,
    depth_sigma,
    kabsch,
    point_covariance,
    project,
    registration_information,
    rigid_jacobian,
    transform_points,
)
from slam.odometry.matching import hamming_distance, match_descriptors, match_features, unpack_bits
from slam.odometry.ransac import RansacResult, ransac_rigid, refine_rigid
from slam.odometry.registration import RegistrationResult, register

__all__ = [
    "FeatureConfig",
    "FrameFeatures",
    "Keyframe",
    "KeyframeEdge",
    "MatchConfig",
    "OdometryConfig",
    "RGBDOdometry",
    "RansacConfig",
    "RansacResult",
    "RegistrationConfig",
    "RegistrationResult",
    "TrackResult",
    "TrackStatus",
    "backproject",
    "bucket_keypoints",
    "depth_sigma",
    "extract_features",
    "hamming_distance",
    "kabsch",
    "match_descriptors",
    "match_features",
    "point_covariance",
    "project",
    "ransac_rigid",
    "refine_rigid",
    "register",
    "registration_information",
    "rigid_jacobian",
    "transform_points",
    "unpack_bits",
]
