"""RGB-D odometry front end: frame-to-keyframe tracking, keyframe selection, tracking-loss handling.

docs/pipeline.md, "What each stage does" (1, 2), describes the policy. ``track`` never raises for a bad frame;
the world is the first keyframe's camera.

Example:
    >>> import numpy as np
    >>> from slam.io.frame import RGBDFrame
    >>> K = np.array([[585., 0, 320], [0, 585., 240], [0, 0, 1]])
    >>> frame = RGBDFrame(0, 0.0, np.zeros((480, 640, 3), np.uint8), np.zeros((480, 640), np.float32), K)
    >>> odo = RGBDOdometry()
    >>> res = odo.track(frame)
    >>> res.status.name, res.pose.shape, len(odo.keyframes)
    ('LOST', torch.Size([7]), 0)
"""
from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import dataclass
from enum import Enum

import cv2
import numpy as np
import torch

from slam.io.frame import RGBDFrame
from slam.lie import se3_between, se3_compose, se3_identity, so3_log
from slam.odometry.config import OdometryConfig
from slam.odometry.features import FrameFeatures, extract_features
from slam.odometry.registration import RegistrationResult, register

Tensor = torch.Tensor
logger = logging.getLogger(__name__)

__all__ = ["Keyframe", "KeyframeEdge", "RGBDOdometry", "TrackResult", "TrackStatus"]


def _describe_frame(frame: RGBDFrame) -> str:
    # the index is the run's (it shifts with --frame-step): the stamp and the image find the frame in its list
    path = getattr(frame, "rgb_path", None)
    return (f"frame {int(frame.index)} (t {float(frame.timestamp):.6f}"
            + (f", {os.path.basename(path)}" if path else "") + ")")


class TrackStatus(Enum):
    """State of the tracker after a frame."""

    INITIALIZED = "initialized"  # the first usable frame: it became keyframe 0 at the world origin
    OK = "ok"  # registered against its keyframe
    LOST = "lost"  # not registered: pose predicted by constant velocity (or identity before init)
    RECOVERED = "recovered"  # registered again after one or more LOST frames


@dataclass
class KeyframeEdge:
    """Odometry constraint between consecutive keyframes ``i -> j``.

    Attributes:
        i: id of the older keyframe.
        j: id of the new keyframe.
        T_ij: ``(7,)`` float64 pose of keyframe j in keyframe i.
        information: ``(6, 6)`` float64 information of ``T_ij`` (right perturbation ``T_ij exp(xi)``, ``[rho, phi]``).
        weak: True for an edge forced after a tracking loss (constant-velocity guess, tiny information).
    """

    i: int
    j: int
    T_ij: Tensor
    information: Tensor
    weak: bool = False


@dataclass
class Keyframe:
    """A keyframe kept by the front end.

    Attributes:
        id: 0, 1, 2, ... in creation order.
        frame_index: index of the input frame it was made from.
        timestamp: that frame's timestamp.
        pose: ``(7,)`` float64 world-from-camera odometry pose.
        features: its :class:`~slam.odometry.features.FrameFeatures` (what loop verification needs).
        rgb: ``(h, w, 3)`` uint8 RGB image, resized by ``OdometryConfig.keyframe_rgb_scale`` to bound memory.
    """

    id: int
    frame_index: int
    timestamp: float
    pose: Tensor
    features: FrameFeatures
    rgb: np.ndarray


@dataclass
class TrackResult:
    """What :meth:`RGBDOdometry.track` reports for one frame.

    Attributes:
        index: the frame's index.
        timestamp: the frame's timestamp.
        pose: ``(7,)`` float64 world-from-camera estimate.
        keyframe_id: the keyframe the frame is expressed relative to (-1 before the first keyframe).
        T_kf_frame: ``(7,)`` float64 pose of the frame in that keyframe.
        is_keyframe: this frame became a new keyframe.
        status: :class:`TrackStatus`.
        reason: why the frame is LOST / RECOVERED or a keyframe was made ("" when plainly OK).
        num_inliers: RANSAC inliers of the registration (0 when LOST).
        edge: the last odometry edge this call created, if any (``edge.j == keyframe_id``).
        inlier_rmse: 3D RMSE (metres) of the inliers of the registration that placed the frame (NaN if none).
    """

    index: int
    timestamp: float
    pose: Tensor
    keyframe_id: int
    T_kf_frame: Tensor
    is_keyframe: bool
    status: TrackStatus
    reason: str
    num_inliers: int
    edge: KeyframeEdge | None = None
    inlier_rmse: float = math.nan


@dataclass
class _LastFrame:
    """The previous tracked frame, kept so it can be promoted to a keyframe."""

    index: int
    timestamp: float
    rgb: np.ndarray
    features: FrameFeatures
    T_kf: Tensor
    information: Tensor


class RGBDOdometry:
    """Frame-to-keyframe RGB-D odometry (see the module docstring).

    Args:
        config: :class:`~slam.odometry.config.OdometryConfig`.

    Attributes:
        keyframes: every keyframe created so far (features + downsized RGB).
        edges: every odometry edge between consecutive keyframes.
        stage_seconds: accumulated wall seconds per stage: ``features``, ``matching``, ``ransac`` and
            ``tracking_other`` (the rest of :meth:`track`).
    """

    def __init__(self, config: OdometryConfig | None = None):
        self.config = config or OdometryConfig()
        self.keyframes: list[Keyframe] = []
        self.edges: list[KeyframeEdge] = []
        self.stage_seconds = {"features": 0.0, "matching": 0.0, "ransac": 0.0, "tracking_other": 0.0}
        self._T_kf_last = se3_identity(dtype=torch.float64)
        self._velocity = se3_identity(dtype=torch.float64)
        self._last: _LastFrame | None = None
        self._lost_count = 0

    @property
    def keyframe(self) -> Keyframe | None:
        """The current reference keyframe (None before the first one)."""
        return self.keyframes[-1] if self.keyframes else None

    def _add_keyframe(self, index: int, timestamp: float, pose: Tensor, features: FrameFeatures,
                      rgb: np.ndarray) -> Keyframe:
        s = self.config.keyframe_rgb_scale
        if s != 1.0 and rgb.size:
            h, w = rgb.shape[:2]
            rgb = cv2.resize(rgb, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
        else:
            rgb = rgb.copy()
        kf = Keyframe(id=len(self.keyframes), frame_index=index, timestamp=timestamp, pose=pose,
                      features=features, rgb=rgb)
        self.keyframes.append(kf)
        return kf

    def _new_keyframe_with_edge(self, index, timestamp, T_kf: Tensor, information: Tensor,
                                features: FrameFeatures, rgb: np.ndarray, weak: bool = False) -> KeyframeEdge:
        old = self.keyframe
        new = self._add_keyframe(index, timestamp, se3_compose(old.pose, T_kf), features, rgb)
        edge = KeyframeEdge(i=old.id, j=new.id, T_ij=T_kf.clone(), information=information.clone(), weak=weak)
        self.edges.append(edge)
        self._T_kf_last = se3_identity(dtype=torch.float64)
        return edge

    def _extract(self, frame: RGBDFrame, features: FrameFeatures | None = None):
        feats = features
        if feats is None:
            try:
                feats = extract_features(frame.rgb, frame.depth, frame.K, self.config.features)
            except (ValueError, TypeError, cv2.error) as exc:
                return None, f"unusable frame: {exc}"
        if feats.num_valid < self.config.min_valid_points:
            return feats, (f"too few keypoints with valid depth, in range and off depth edges ({feats.num_valid} "
                           f"of {len(feats)}; need {self.config.min_valid_points})")
        return feats, ""

    def _lost(self, frame: RGBDFrame, feats: FrameFeatures | None, reason: str) -> TrackResult:
        """LOST: constant-velocity pose; maybe force a keyframe after too many lost frames."""
        index, ts = int(frame.index), float(frame.timestamp)
        kf = self.keyframe
        where = _describe_frame(frame)
        if kf is None:
            logger.warning("%s lost before initialisation: %s", where, reason)
            return TrackResult(index, ts, se3_identity(dtype=torch.float64), -1,
                               se3_identity(dtype=torch.float64), False, TrackStatus.LOST, reason, 0)
        self._lost_count += 1
        T_kf = se3_compose(self._T_kf_last, self._velocity)
        self._T_kf_last = T_kf
        pose = se3_compose(kf.pose, T_kf)
        edge = None
        usable = feats is not None and feats.num_valid >= self.config.min_valid_points
        # every max_lost_frames lost frames in a row (while the frame itself has usable features)
        if self._lost_count % self.config.max_lost_frames == 0 and usable:
            info = self.config.weak_edge_information * torch.eye(6, dtype=torch.float64)
            edge = self._new_keyframe_with_edge(index, ts, T_kf, info, feats, frame.rgb, weak=True)
            reason += (f"; lost for {self._lost_count} frames: new keyframe {edge.j} at the "
                       f"constant-velocity pose (weak edge)")
        self._last = None  # an untracked frame must not be promoted
        logger.warning("%s lost: %s", where, reason)
        T_out = se3_identity(dtype=torch.float64) if edge is not None else T_kf
        return TrackResult(index, ts, pose, self.keyframe.id, T_out, edge is not None, TrackStatus.LOST, reason, 0,
                           edge)

    def _add_seconds(self, res: RegistrationResult) -> None:
        for k, v in res.seconds.items():
            self.stage_seconds[k] = self.stage_seconds.get(k, 0.0) + v

    def track(self, frame: RGBDFrame, features: FrameFeatures | None = None) -> TrackResult:
        """Estimate the pose of the next frame.

        Args:
            frame: the next :class:`~slam.io.frame.RGBDFrame` (RGB ``(H, W, 3)`` uint8, depth ``(H, W)``
                metres with 0 = invalid, ``K (3, 3)``).
            features: the frame's :func:`~slam.odometry.features.extract_features` with ``config.features``
                if already extracted (e.g. by the reading thread); None: extracted here.

        Returns:
            :class:`TrackResult`; bad frames give ``status=LOST`` with a reason, never an exception.

        Raises:
            ValueError: ``features`` of another image size than the frame's.
        """
        if features is not None and tuple(features.image_size) != tuple(frame.depth.shape[:2]):
            raise ValueError(f"features of a {features.image_size} image given with a frame of "
                             f"{tuple(frame.depth.shape[:2])}")
        t0 = time.perf_counter()
        before = sum(self.stage_seconds.values())
        out = self._track(frame, features)
        spent = time.perf_counter() - t0
        self.stage_seconds["tracking_other"] += max(0.0, spent - (sum(self.stage_seconds.values()) - before))
        return out

    def _track(self, frame: RGBDFrame, features: FrameFeatures | None) -> TrackResult:
        t0 = time.perf_counter()
        feats, reason = self._extract(frame, features)
        self.stage_seconds["features"] += time.perf_counter() - t0
        index, ts = int(frame.index), float(frame.timestamp)
        if reason:
            return self._lost(frame, feats, reason)
        cfg = self.config
        if self.keyframe is None:
            pose = se3_identity(dtype=torch.float64)
            kf = self._add_keyframe(index, ts, pose, feats, frame.rgb)
            self._last = _LastFrame(index, ts, frame.rgb, feats, pose, torch.zeros(6, 6, dtype=torch.float64))
            logger.info("frame %d: initialised keyframe 0 with %d points", index, feats.num_valid)
            return TrackResult(index, ts, pose, kf.id, pose.clone(), True, TrackStatus.INITIALIZED,
                               "first keyframe", 0)

        prior = se3_compose(self._T_kf_last, self._velocity)
        res: RegistrationResult = register(self.keyframe.features, feats, cfg.registration, prior_ab=prior)
        self._add_seconds(res)
        edge = None
        notes = []
        last = self._last
        if not res.success and last is not None and last.index != self.keyframe.frame_index:
            # the keyframe is out of reach: promote the last tracked frame and re-track against it
            first_reason = res.reason
            edge = self._new_keyframe_with_edge(last.index, last.timestamp, last.T_kf, last.information,
                                                last.features, last.rgb)
            res = register(self.keyframe.features, feats, cfg.registration, prior_ab=self._velocity)
            self._add_seconds(res)
            notes.append(f"keyframe {edge.i} failed ({first_reason}): previous frame {last.index} "
                         f"promoted to keyframe {edge.j}")
        if not res.success:
            out = self._lost(frame, feats, "; ".join(notes + [f"registration failed: {res.reason}"]))
            if edge is not None and out.edge is None:
                out.edge = edge
            return out

        T_kf = res.T_ab
        kf = self.keyframe
        self._velocity = se3_between(self._T_kf_last, T_kf)
        status = TrackStatus.RECOVERED if self._lost_count > 0 else TrackStatus.OK
        if self._lost_count > 0:
            notes.append(f"recovered after {self._lost_count} lost frames")
        self._lost_count = 0
        pose = se3_compose(kf.pose, T_kf)
        is_kf = False
        if edge is None:
            trans = float(T_kf[:3].norm())
            rot = math.degrees(float(so3_log(T_kf[3:]).norm()))
            ratio = res.num_inliers / max(kf.features.num_valid, 1)
            why = []
            if trans > cfg.keyframe_translation:
                why.append(f"moved {trans:.3f} m")
            if rot > cfg.keyframe_rotation_deg:
                why.append(f"turned {rot:.1f} deg")
            if res.num_inliers < cfg.keyframe_min_inliers:
                why.append(f"{res.num_inliers} inliers")
            if ratio < cfg.keyframe_min_inlier_ratio:
                why.append(f"inlier ratio {ratio:.2f}")
            if why:
                edge = self._new_keyframe_with_edge(index, ts, T_kf, res.information, feats, frame.rgb)
                is_kf = True
                notes.append("new keyframe: " + ", ".join(why))
        if not is_kf:
            self._T_kf_last = T_kf
        self._last = _LastFrame(index, ts, frame.rgb, feats, self._T_kf_last, res.information)
        reason_out = "; ".join(notes)
        if status is TrackStatus.RECOVERED or edge is not None:  # every keyframe decision (--verbose shows them)
            logger.info("frame %d: %s", index, reason_out)
        T_out = se3_identity(dtype=torch.float64) if is_kf else T_kf
        return TrackResult(index, ts, pose, self.keyframe.id, T_out, is_kf, status, reason_out, res.num_inliers, edge,
                           res.inlier_rmse)
