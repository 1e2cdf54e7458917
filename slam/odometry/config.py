"""Typed settings of the RGB-D odometry: every threshold lives here, with its default explained (measured:
docs/results.md, "Odometry"), and the configs' shared ``check_*`` helpers.

Example:
    >>> cfg = OdometryConfig()
    >>> cfg.features.detector, cfg.registration.ransac.confidence
    ('orb', 0.999)
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

__all__ = ["DETECTORS", "MATCH_METHODS", "FeatureConfig", "MatchConfig", "OdometryConfig",
           "RansacConfig", "RegistrationConfig"]

# The one list of each choice (``__post_init__`` refuses any other name when the config is built).
DETECTORS = ("orb", "sift")  # FeatureConfig.detector (slam.odometry.features)
MATCH_METHODS = ("smnn", "snn", "mnn")  # MatchConfig.method (slam.odometry.matching, Kornia's match_*)


def _range_text(lo, hi, lo_open: bool) -> str:
    if lo is not None and hi is not None:
        return f"in {'(' if lo_open else '['}{lo}, {hi}]"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {lo}"
    if hi is not None:
        return f"<= {hi}"
    return ""


def check_int(owner: str, name: str, value, lo: int | None = None, hi: int | None = None) -> None:
    """ValueError naming ``owner.name`` unless ``value`` is an integer (not a bool) in ``[lo, hi]``."""
    if (isinstance(value, bool) or not isinstance(value, numbers.Integral) or (lo is not None and value < lo)
            or (hi is not None and value > hi)):
        rng = _range_text(lo, hi, False)
        raise ValueError(f"{owner}.{name} must be an integer{' ' + rng if rng else ''}, got {value!r}")


def check_number(owner: str, name: str, value, lo: float | None = None, hi: float | None = None, *,
                 lo_open: bool = False, finite: bool = False) -> None:
    """ValueError naming ``owner.name`` unless ``value`` is a real number (not NaN, not a bool) within
    ``[lo, hi]`` (``lo_open``: ``(lo, hi]``). ``finite=False`` lets ``inf`` pass where the bounds do (an
    infinite threshold switches a bound off)."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and not math.isnan(value)
    if ok and finite:
        ok = math.isfinite(value)
    if ok and lo is not None:
        ok = value > lo if lo_open else value >= lo
    if ok and hi is not None:
        ok = value <= hi
    if not ok:
        what = (_range_text(lo, hi, lo_open) or "a number") + (" and finite" if finite else "")
        raise ValueError(f"{owner}.{name} must be {what}, got {value!r}")


def _finite_numbers(values) -> tuple | None:
    """``values`` as a tuple of finite reals (any sequence or 1-D array), or None when it is not one."""
    try:
        out = tuple(values)
    except TypeError:
        return None
    ok = all(isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) for v in out)
    return out if ok else None


def check_bool(owner: str, name: str, value) -> None:
    """ValueError naming ``owner.name`` unless ``value`` is True or False."""
    if not isinstance(value, bool):
        raise ValueError(f"{owner}.{name} must be True or False, got {value!r}")


def check_choice(owner: str, name: str, value, allowed: tuple) -> None:
    """ValueError naming ``owner.name`` unless ``value`` is one of ``allowed`` (exactly: case matters)."""
    if not isinstance(value, str) or value not in allowed:
        raise ValueError(f"{owner}.{name} must be one of {', '.join(map(repr, allowed))}, got {value!r}")


@dataclass(frozen=True)
class FeatureConfig:
    """Keypoint detection, description and back-projection."""

    detector: str = "orb"  # "orb" (OpenCV ORB, 256-bit binary) or "sift" (OpenCV SIFT, 128-d float, ~10x slower)
    image_scale: float = 1.0  # detection on the grey image resized by this; keypoints in full-size pixels
    detect_features: int = 2000  # candidates asked from the detector before bucketing
    # cap after bucketing: the strongest of each grid cell, so that a RANSAC fit is not from one textured corner
    max_features: int = 1000
    grid_rows: int = 6
    grid_cols: int = 8
    orb_scale_factor: float = 1.2  # ORB pyramid step and levels (OpenCV's defaults)
    orb_levels: int = 8
    fast_threshold: int = 12  # OpenCV's is 20: low-texture walls still get corners
    min_depth: float = 0.3  # m; Kinect v1 measures from ~0.4 m
    max_depth: float = 4.0  # m; beyond, its noise exceeds 3 cm
    # a keypoint gets a 3D point only when its (2r+1)^2 window is valid and within max_depth_jump * z of the
    # centre (not on a silhouette, where colour and depth disagree)
    depth_window_radius: int = 1
    max_depth_jump: float = 0.05
    keypoint_sigma_px: float = 1.0  # pixel noise at pyramid level 0; level l: sigma * scale_factor^l
    # (fx, fy, cx, cy) of the colour camera when K is the depth camera's: depth is warped into the colour camera
    # (slam.odometry.depth_registration); None: registered (colour pixel = depth pixel)
    rgb_intrinsics: tuple[float, float, float, float] | None = None
    # the depth camera's centre in the colour camera's frame (m), parallel axes: p_rgb = p_depth + t
    rgb_from_depth_translation: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        n = "FeatureConfig"
        check_choice(n, "detector", self.detector, DETECTORS)
        check_number(n, "image_scale", self.image_scale, 0, lo_open=True, finite=True)
        check_int(n, "detect_features", self.detect_features, 1)
        check_int(n, "max_features", self.max_features, 1)
        check_int(n, "grid_rows", self.grid_rows, 1)
        check_int(n, "grid_cols", self.grid_cols, 1)
        check_number(n, "orb_scale_factor", self.orb_scale_factor, 1, lo_open=True, finite=True)  # OpenCV: > 1
        check_int(n, "orb_levels", self.orb_levels, 1)
        check_int(n, "fast_threshold", self.fast_threshold, 0, 255)  # an 8-bit intensity difference
        check_number(n, "min_depth", self.min_depth, 0, finite=True)
        check_number(n, "max_depth", self.max_depth, 0, lo_open=True)
        if not self.max_depth > self.min_depth:
            raise ValueError(f"FeatureConfig.max_depth ({self.max_depth!r}) must be > FeatureConfig.min_depth "
                             f"({self.min_depth!r})")
        check_int(n, "depth_window_radius", self.depth_window_radius, 0)
        check_number(n, "max_depth_jump", self.max_depth_jump, 0, lo_open=True)
        check_number(n, "keypoint_sigma_px", self.keypoint_sigma_px, 0, lo_open=True, finite=True)
        if self.rgb_intrinsics is not None:
            k = _finite_numbers(self.rgb_intrinsics)
            if k is None or len(k) != 4 or not (k[0] > 0 and k[1] > 0):
                raise ValueError("FeatureConfig.rgb_intrinsics must be None or 4 finite numbers (fx, fy, cx, cy) "
                                 f"with fx, fy > 0, got {self.rgb_intrinsics!r}")
        t = _finite_numbers(self.rgb_from_depth_translation)
        if t is None or len(t) != 3:
            raise ValueError("FeatureConfig.rgb_from_depth_translation must be 3 finite numbers (metres), got "
                             f"{self.rgb_from_depth_translation!r}")


@dataclass(frozen=True)
class MatchConfig:
    """Descriptor matching (always Kornia's matchers, ``kornia.feature.match_*``)."""

    method: str = "smnn"  # "smnn" (mutual NN + ratio test both ways), "snn" (ratio test), "mnn" (mutual NN)
    ratio: float = 0.9  # best / second-best descriptor distance (snn, smnn)
    max_hamming: float = 64.0  # distance cap, bits of 256 (binary descriptors)
    max_l2: float = 0.7  # distance cap of unit float descriptors
    # a keypoint matches only those within this many pixels (at 640x480) of its position predicted by the motion
    # prior; 0: unguided
    guided_radius_px: float = 40.0

    def __post_init__(self) -> None:
        n = "MatchConfig"
        check_choice(n, "method", self.method, MATCH_METHODS)
        check_number(n, "ratio", self.ratio, 0, 1, lo_open=True)  # 1: the ratio test passes everything
        check_number(n, "max_hamming", self.max_hamming, 0, lo_open=True)  # inf: no cap
        check_number(n, "max_l2", self.max_l2, 0, lo_open=True)
        check_number(n, "guided_radius_px", self.guided_radius_px, 0)  # 0: unguided


@dataclass(frozen=True)
class RansacConfig:
    """3D-3D RANSAC over 3-point hypotheses, then a refinement on the inliers."""

    batch_size: int = 64  # hypotheses scored at once, until the adaptive count is reached
    min_iterations: int = 64
    max_iterations: int = 1024
    confidence: float = 0.999  # that one all-inlier sample was drawn (the adaptive count)
    # inlier: |T p_src - p_dst| < max(inlier_threshold, inlier_sigmas * the two points' combined depth std)
    inlier_threshold: float = 0.03  # m
    inlier_sigmas: float = 3.0
    min_sample_area: float = 1e-4  # m^2: a smaller sample triangle is degenerate
    min_inliers: int = 12  # fewer: "too few inliers"
    min_spread: float = 0.01  # m: second singular value of the inliers below which they are collinear
    # Gauss-Newton steps on the depth-along-the-ray Mahalanobis error, Huber kernel; 0: the weighted Kabsch fit
    refine_iterations: int = 5
    huber_delta: float = 2.0
    seed: int = 0  # of the hypothesis sampler (a fresh torch.Generator per call)

    def __post_init__(self) -> None:
        n = "RansacConfig"
        check_int(n, "batch_size", self.batch_size, 1)
        check_int(n, "max_iterations", self.max_iterations, 1)
        check_int(n, "min_iterations", self.min_iterations, 0, self.max_iterations)
        check_number(n, "confidence", self.confidence, 0, 1, lo_open=True)
        check_number(n, "inlier_threshold", self.inlier_threshold, 0, lo_open=True)
        check_number(n, "inlier_sigmas", self.inlier_sigmas, 0)
        check_number(n, "min_sample_area", self.min_sample_area, 0, finite=True)
        check_int(n, "min_inliers", self.min_inliers, 3)  # a rigid fit needs 3 points
        check_number(n, "min_spread", self.min_spread, 0, finite=True)
        check_int(n, "refine_iterations", self.refine_iterations, 0)
        check_number(n, "huber_delta", self.huber_delta, 0, lo_open=True)
        check_int(n, "seed", self.seed)


@dataclass(frozen=True)
class RegistrationConfig:
    """Two-frame registration: matching + RANSAC + the checks that decide success."""

    matching: MatchConfig = field(default_factory=MatchConfig)
    ransac: RansacConfig = field(default_factory=RansacConfig)
    min_matches: int = 20  # fewer: "too few matches", before RANSAC
    min_inliers: int = 20  # success needs this many inliers after refinement ...
    max_rmse: float = 0.05  # ... and an inlier RMSE (m) below this
    # Kinect v1 depth noise sigma(z) = a + b (z - c)^2 (Nguyen et al. 2012), metres
    depth_sigma_a: float = 0.0012
    depth_sigma_b: float = 0.0019
    depth_sigma_c: float = 0.4

    def __post_init__(self) -> None:
        n = "RegistrationConfig"
        check_int(n, "min_matches", self.min_matches, 0)
        check_int(n, "min_inliers", self.min_inliers, 0)
        check_number(n, "max_rmse", self.max_rmse, 0, lo_open=True)  # inf: no check
        check_number(n, "depth_sigma_a", self.depth_sigma_a, 0, lo_open=True, finite=True)  # sigma(z) > 0
        check_number(n, "depth_sigma_b", self.depth_sigma_b, 0, finite=True)
        check_number(n, "depth_sigma_c", self.depth_sigma_c, finite=True)


@dataclass(frozen=True)
class OdometryConfig:
    """Frame-to-keyframe tracking and keyframe selection."""

    features: FeatureConfig = field(default_factory=FeatureConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    min_valid_points: int = 30  # keypoints with depth a frame needs to be tracked or to become a keyframe
    # a new keyframe when the frame moved more than this from its keyframe (m / degrees) ...
    keyframe_translation: float = 0.15
    keyframe_rotation_deg: float = 12.0
    # ... or has fewer inliers than this, or than this fraction of the keyframe's valid keypoints (a small
    # overlap costs more than an extra keyframe)
    keyframe_min_inliers: int = 180
    keyframe_min_inlier_ratio: float = 0.15
    # after this many lost frames a keyframe is forced at the constant-velocity pose, by a weak edge
    # (weak_edge_information * I), so that tracking can restart
    max_lost_frames: int = 3
    weak_edge_information: float = 1e-2
    keyframe_rgb_scale: float = 0.5  # keyframe images kept at this scale (the descriptor resizes to 224 px)

    def __post_init__(self) -> None:
        n = "OdometryConfig"
        check_int(n, "min_valid_points", self.min_valid_points, 0)
        check_number(n, "keyframe_translation", self.keyframe_translation, 0)  # inf: never on motion
        check_number(n, "keyframe_rotation_deg", self.keyframe_rotation_deg, 0)
        check_int(n, "keyframe_min_inliers", self.keyframe_min_inliers, 0)
        check_number(n, "keyframe_min_inlier_ratio", self.keyframe_min_inlier_ratio, 0, 1)
        check_int(n, "max_lost_frames", self.max_lost_frames, 1)
        check_number(n, "weak_edge_information", self.weak_edge_information, 0, lo_open=True, finite=True)
        check_number(n, "keyframe_rgb_scale", self.keyframe_rgb_scale, 0, 1, lo_open=True)
