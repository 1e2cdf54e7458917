"""The RGB-D SLAM system: odometry front end + attention-guided loop closure + pose-graph back end.

Data flows one way: frame -> odometry (:mod:`slam.odometry`) -> keyframe -> descriptor
(:class:`attnloop.AttentionDescriptor`) -> index (:class:`attnloop.index.LoopCandidateDetector`) ->
geometric verification (:func:`slam.odometry.register`) -> pose graph (:mod:`slam.graph`) -> trajectory.

Only keyframes enter the pose graph; every other frame is stored as a pose relative to its keyframe, so
after the final optimisation each input frame gets ``T_world_kf (optimised) * T_kf_frame``.

Example:
    >>> import numpy as np
    >>> from slam.io.frame import RGBDFrame
    >>> cfg = SLAMConfig()
    >>> cfg.loop.enabled = False
    >>> slam = RGBDSLAM(cfg)
    >>> K = np.array([[525., 0, 319.5], [0, 525., 239.5], [0, 0, 1]])
    >>> state = slam.track(RGBDFrame(0, 0.0, np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64), np.float32), K))
    >>> state.status
    'lost'
    >>> result = slam.finish()
    >>> result.trajectory.poses.shape, result.num_keyframes
    (torch.Size([1, 7]), 0)
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np
import torch

from slam.config import SLAMConfig
from slam.graph import PoseGraph, optimize
from slam.graph.optimizer import OptimizationResult
from slam.io.frame import RGBDFrame
from slam.io.trajectory import Trajectory
from slam.lie import se3_between, se3_compose, se3_identity, so3_log
from slam.odometry import RGBDOdometry
from slam.odometry.depth_registration import depth_camera_poses, rig_pose
from slam.odometry.frontend import Keyframe, KeyframeEdge, TrackStatus
from slam.odometry.registration import register
from slam.timing import StageTimer

logger = logging.getLogger(__name__)
Tensor = torch.Tensor

__all__ = ["RGBDSLAM", "SLAMResult", "FrameState", "LoopClosure", "LoopQuery"]


@dataclass
class FrameState:
    """What :meth:`RGBDSLAM.track` reports for one frame.

    Attributes:
        index: input order of the frame.
        timestamp: its timestamp.
        pose: ``(7,)`` float64 current (odometry-chained) world-from-camera estimate of the depth camera
            (the frame of the input ``K``; see ``FeatureConfig.rgb_intrinsics`` for unregistered frames).
        status: ``"initialized" | "ok" | "lost" | "recovered" | "skipped"``.
        reason: why it is lost / skipped / a keyframe ("" when plainly tracked).
        keyframe_id: the keyframe it is expressed relative to (-1 before the first keyframe).
        new_keyframes: ids of keyframes created by this call.
        new_loops: loops accepted during this call.
        num_inliers: inliers of the registration that placed the frame (0 when none did).
        inlier_rmse: their 3D RMSE in metres (NaN when no registration placed the frame).
    """

    index: int
    timestamp: float
    pose: Tensor
    status: str
    reason: str
    keyframe_id: int
    new_keyframes: List[int] = field(default_factory=list)
    new_loops: List["LoopClosure"] = field(default_factory=list)
    num_inliers: int = 0
    inlier_rmse: float = math.nan


@dataclass
class LoopClosure:
    """An accepted, geometrically verified loop between keyframes ``kf_a < kf_b``.

    Attributes:
        kf_a, kf_b: keyframe ids; the edge measures ``T_ab`` (pose of b in a).
        frame_a, frame_b: input indices of the two keyframes.
        timestamp_a, timestamp_b: their timestamps.
        similarity: descriptor cosine similarity of the pair.
        num_inliers: RANSAC inliers of the verification.
        T_ab: ``(7,)`` float64 measured relative pose, in the tracked camera's frame (the colour camera's
            when the frames are unregistered).
    """

    kf_a: int
    kf_b: int
    frame_a: int
    frame_b: int
    timestamp_a: float
    timestamp_b: float
    similarity: float
    num_inliers: int
    T_ab: Tensor


@dataclass
class LoopQuery:
    """One query of the keyframe database (for the loop-closure evaluation).

    Attributes:
        kf: query keyframe id.
        top_kf: most similar eligible keyframe id (-1 when none was eligible).
        top_score: its similarity (``-inf`` when none).
        threshold: the query's adaptive threshold.
        candidates: ids that passed the threshold (and consistency) and were sent to verification.
        verified: ids accepted by geometric verification.
        rejections: ``{candidate id: reason}`` for candidates that failed verification.
    """

    kf: int
    top_kf: int
    top_score: float
    threshold: float
    candidates: List[int]
    verified: List[int]
    rejections: Dict[int, str] = field(default_factory=dict)


@dataclass
class SLAMResult:
    """What :meth:`RGBDSLAM.finish` returns.

    Attributes:
        trajectory: one optimised pose per input frame, in input order.
        odometry_trajectory: the same frames before pose-graph optimisation.
        keyframe_trajectory: optimised keyframe poses (timestamps of the keyframes).
        keyframe_frames: ``(M,)`` input index of each keyframe.
        loops: accepted loops.
        queries: one entry per loop-database query.
        graph: the optimised keyframe pose graph (None when there were no keyframes).
        optimization: the optimiser's result (None when nothing was optimised).
        num_frames, num_keyframes, num_lost, num_skipped: counts.
        timings: seconds and calls per stage.
    """

    trajectory: Trajectory
    odometry_trajectory: Trajectory
    keyframe_trajectory: Trajectory
    keyframe_frames: Tensor
    loops: List[LoopClosure]
    queries: List[LoopQuery]
    graph: Optional[PoseGraph]
    optimization: Optional[OptimizationResult]
    num_frames: int
    num_keyframes: int
    num_lost: int
    num_skipped: int
    timings: Dict[str, Dict[str, float]]


@dataclass
class _FrameRecord:
    index: int
    timestamp: float
    keyframe_id: int
    T_kf_frame: Tensor
    status: str


def _rotation_deg(q: Tensor) -> float:
    return math.degrees(float(so3_log(q).norm()))


class RGBDSLAM:
    """Attention-guided loop-closing RGB-D SLAM.

    Args:
        config: :class:`slam.config.SLAMConfig`.
        descriptor: an already built descriptor model mapping ``(1, 3, H, W)`` uint8 images to ``(1, D)``
            L2-normalised descriptors (default: :class:`attnloop.AttentionDescriptor` built from
            ``config.loop.descriptor``; built lazily at the first keyframe).

    Call :meth:`track` once per frame in input order (or :meth:`skip` for a frame that could not be read),
    then :meth:`finish`.
    """

    def __init__(self, config: Optional[SLAMConfig] = None, descriptor: Optional[torch.nn.Module] = None):
        self.config = config or SLAMConfig()
        self.odometry = RGBDOdometry(self.config.odometry)
        self.timer = StageTimer()
        self._descriptor = descriptor
        self._detector = None
        if self.config.loop.enabled:
            from attnloop.index import LoopCandidateDetector

            self._detector = LoopCandidateDetector(self.config.loop.detector)
            if self._descriptor is None:
                self._descriptor = self._build_descriptor()
        self._frames: List[_FrameRecord] = []
        self._kf_poses: List[Tensor] = []  # odometry pose of each keyframe
        self._edges: List[KeyframeEdge] = []
        self._loops: List[LoopClosure] = []
        self._queries: List[LoopQuery] = []
        self._kf_of_frame: Dict[int, int] = {}  # the detector's ids are frame indices
        self._num_kf_seen = 0
        self._num_lost = 0
        self._num_skipped = 0
        self._finished = False
        # The front end tracks the camera whose pixels the keypoints live in: the colour camera when the
        # frames are unregistered (``odometry.features.rgb_intrinsics``). Poses are reported for the
        # depth camera, the frame of the input K and of depth-based ground truth (7-Scenes'), by the
        # change of frame T_rgb_depth^-1 * P * T_rgb_depth (the world stays the first camera's).
        feats = self.config.odometry.features
        self._T_rgb_depth = None
        if feats.rgb_intrinsics is not None and any(float(x) != 0.0 for x in feats.rgb_from_depth_translation):
            self._T_rgb_depth = rig_pose(feats.rgb_from_depth_translation)

    # ------------------------------------------------------------------------------------------
    def _build_descriptor(self) -> torch.nn.Module:
        from attnloop import AttentionDescriptor

        d = self.config.loop.descriptor
        with self.timer("descriptor_init"):
            model = AttentionDescriptor(backbone=d.backbone, fusion=d.fusion, num_rnn=d.num_rnn, seed=d.seed,
                                        pretrained=d.pretrained, weights=d.weights)
            model.eval()
            if d.device:
                model = model.to(d.device)
        return model

    @property
    def keyframes(self) -> List[Keyframe]:
        """The odometry's keyframes (features and downsized RGB)."""
        return self.odometry.keyframes

    @property
    def loops(self) -> List[LoopClosure]:
        """Loops accepted so far."""
        return list(self._loops)

    # ------------------------------------------------------------------------------------------
    def track(self, frame: RGBDFrame) -> FrameState:
        """Process the next frame.

        Args:
            frame: :class:`~slam.io.frame.RGBDFrame` (RGB ``(H, W, 3)`` uint8, depth ``(H, W)`` metres).

        Returns:
            :class:`FrameState`. Bad frames (no depth, no texture) are a ``"lost"`` state, never an error.
        """
        if self._finished:
            raise RuntimeError("track() called after finish(); create a new RGBDSLAM")
        with self.timer("odometry"):
            res = self.odometry.track(frame)
        status = res.status.value
        if res.status is TrackStatus.LOST:
            self._num_lost += 1
        self._frames.append(_FrameRecord(int(frame.index), float(frame.timestamp), res.keyframe_id,
                                         res.T_kf_frame.detach().to(torch.float64).cpu(), status))
        if res.edge is not None:
            self._edges.append(res.edge)
        state = FrameState(int(frame.index), float(frame.timestamp), self._output_frame(res.pose), status,
                           res.reason, res.keyframe_id, num_inliers=res.num_inliers, inlier_rmse=res.inlier_rmse)
        # every keyframe the front end created during this call (a promoted previous frame included)
        for kf in self.odometry.keyframes[self._num_kf_seen:]:
            self._kf_poses.append(kf.pose.detach().to(torch.float64).cpu())
            state.new_keyframes.append(kf.id)
            if self._detector is not None:
                state.new_loops.extend(self._close_loops(kf))
        self._num_kf_seen = len(self.odometry.keyframes)
        return state

    def skip(self, index: int, timestamp: float, reason: str) -> FrameState:
        """Record a frame that could not be read: it is placed by constant velocity like a lost frame.

        Args:
            index: its input index.
            timestamp: its timestamp.
            reason: why it was skipped (logged and kept).
        """
        logger.warning("frame %d skipped: %s", index, reason)
        self._num_skipped += 1
        if self._frames:
            prev = self._frames[-1]
            kf_id, T = prev.keyframe_id, prev.T_kf_frame
        else:
            kf_id, T = -1, se3_identity(dtype=torch.float64)
        self._frames.append(_FrameRecord(int(index), float(timestamp), kf_id, T.clone(), "skipped"))
        pose = self._output_frame(se3_compose(self._kf_poses[kf_id], T)) if kf_id >= 0 else T.clone()
        return FrameState(int(index), float(timestamp), pose, "skipped", reason, kf_id)

    # ------------------------------------------------------------------------------------------
    @torch.no_grad()
    def _describe(self, kf: Keyframe) -> Tensor:
        img = torch.from_numpy(np.ascontiguousarray(kf.rgb)).permute(2, 0, 1)[None]
        dev = next(iter(self._descriptor.buffers()), None)
        if dev is not None:
            img = img.to(dev.device)
        return self._descriptor(img)[0]

    def _close_loops(self, kf: Keyframe) -> List[LoopClosure]:
        cfg = self.config.loop
        with self.timer("descriptor"):
            desc = self._describe(kf)
        with self.timer("loop_detection"):
            # ids are frame indices so that the exclusion window counts frames, not keyframes
            cands = self._detector.add_and_query(desc, keyframe_id=kf.frame_index, timestamp=kf.timestamp)
        self._kf_of_frame[kf.frame_index] = kf.id
        top_kf = self._kf_of_frame[int(cands.top_ids[0])] if cands.top_ids.numel() else -1
        top_score = float(cands.top_scores[0]) if cands.top_scores.numel() else float("-inf")
        query = LoopQuery(kf.id, top_kf, top_score, float(cands.threshold),
                          [self._kf_of_frame[int(c)] for c in cands.ids[: cfg.max_candidates]], [])
        self._queries.append(query)
        accepted = []
        for cand_id, score in zip(query.candidates, cands.scores[: cfg.max_candidates].tolist()):
            with self.timer("verification"):
                loop, why = self._verify(self.odometry.keyframes[cand_id], kf, float(score))
            if loop is None:
                query.rejections[cand_id] = why
                logger.info("loop candidate %d -> %d rejected: %s", cand_id, kf.id, why)
                continue
            query.verified.append(cand_id)
            self._loops.append(loop)
            accepted.append(loop)
            logger.info("loop accepted: keyframe %d (frame %d) <-> keyframe %d (frame %d), %d inliers",
                        loop.kf_a, loop.frame_a, loop.kf_b, loop.frame_b, loop.num_inliers)
        return accepted

    def _verify(self, a: Keyframe, b: Keyframe, score: float):
        """Geometric verification of the candidate pair (a older, b the query)."""
        cfg = self.config.loop
        res = register(a.features, b.features, cfg.registration)
        if not res.success:
            return None, f"registration failed: {res.reason}"
        if res.num_inliers < cfg.min_inliers:
            return None, f"{res.num_inliers} inliers < {cfg.min_inliers}"
        ratio = res.num_inliers / max(res.num_matches, 1)
        if ratio < cfg.min_inlier_ratio:
            return None, f"inlier ratio {ratio:.2f} < {cfg.min_inlier_ratio}"
        T_ab = res.T_ab.detach().to(torch.float64).cpu()
        dist, rot = float(T_ab[:3].norm()), _rotation_deg(T_ab[3:])
        if dist > cfg.max_translation or rot > cfg.max_rotation_deg:
            return None, f"views too far apart ({dist:.2f} m, {rot:.0f} deg)"
        odo = se3_between(self._kf_poses[a.id], self._kf_poses[b.id])
        diff = se3_between(odo, T_ab)
        dt, dr = float(diff[:3].norm()), _rotation_deg(diff[3:])
        if dt > cfg.max_drift_translation or dr > cfg.max_drift_rotation_deg:
            return None, f"contradicts odometry by {dt:.2f} m / {dr:.0f} deg"
        info = res.information.detach().to(torch.float64).cpu() * cfg.information_scale
        edge = KeyframeEdge(i=a.id, j=b.id, T_ij=T_ab, information=info)
        self._edges.append(edge)
        return LoopClosure(a.id, b.id, a.frame_index, b.frame_index, a.timestamp, b.timestamp, score,
                           res.num_inliers, T_ab), ""

    # ------------------------------------------------------------------------------------------
    def _graph(self) -> Optional[PoseGraph]:
        if not self._kf_poses:
            return None
        poses = torch.stack(self._kf_poses)
        if not self._edges:
            return PoseGraph(poses, torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long),
                             torch.zeros(0, 7, dtype=torch.float64), torch.zeros(0, 6, 6, dtype=torch.float64))
        loops = {(lp.kf_a, lp.kf_b) for lp in self._loops}
        scale = torch.tensor([1.0 if (e.i, e.j) in loops else self.config.backend.odometry_information_scale
                              for e in self._edges], dtype=torch.float64)
        info = torch.stack([e.information.to(torch.float64).cpu() for e in self._edges])
        info = 0.5 * (info + info.transpose(-1, -2)) * scale[:, None, None]
        return PoseGraph(poses,
                         torch.tensor([e.i for e in self._edges], dtype=torch.long),
                         torch.tensor([e.j for e in self._edges], dtype=torch.long),
                         torch.stack([e.T_ij.to(torch.float64).cpu() for e in self._edges]), info)

    def _output_frame(self, poses: Tensor) -> Tensor:
        """Tracked-camera poses ``(..., 7)`` -> depth-camera poses (identity map for registered frames)."""
        if self._T_rgb_depth is None:
            return poses
        return depth_camera_poses(poses, self._T_rgb_depth)

    def _frames_trajectory(self, kf_poses: Tensor) -> Trajectory:
        n = len(self._frames)
        ts = torch.tensor([f.timestamp for f in self._frames], dtype=torch.float64)
        if n == 0:
            return Trajectory(ts, torch.zeros(0, 7, dtype=torch.float64))
        kf = torch.tensor([max(f.keyframe_id, 0) for f in self._frames], dtype=torch.long)
        T = torch.stack([f.T_kf_frame for f in self._frames])
        base = kf_poses[kf] if kf_poses.shape[0] else se3_identity(n, dtype=torch.float64)
        return Trajectory(ts, self._output_frame(se3_compose(base, T)))

    def finish(self) -> SLAMResult:
        """Optimise the keyframe pose graph and return every frame's pose.

        Returns:
            :class:`SLAMResult`.
        """
        self._finished = True
        graph = self._graph()
        opt = None
        kf_odo = torch.stack(self._kf_poses) if self._kf_poses else torch.zeros(0, 7, dtype=torch.float64)
        kf_final = kf_odo
        if graph is not None and graph.num_edges > 0 and self._loops:
            b = self.config.backend
            with self.timer("optimization"):
                opt = optimize(graph, method=b.method, kernel=b.kernel, kernel_width=b.kernel_width,
                               max_iterations=b.max_iterations)
            logger.info("pose graph: %d keyframes, %d edges (%d loops), chi2 %.3g -> %.3g, %s",
                        graph.num_poses, graph.num_edges, len(self._loops), opt.initial_chi2, opt.chi2,
                        opt.status)
            graph = opt.graph
            kf_final = graph.poses
        kf_ts = torch.tensor([kf.timestamp for kf in self.odometry.keyframes], dtype=torch.float64)
        return SLAMResult(
            trajectory=self._frames_trajectory(kf_final),
            odometry_trajectory=self._frames_trajectory(kf_odo),
            keyframe_trajectory=Trajectory(kf_ts, self._output_frame(kf_final.clone())),
            keyframe_frames=torch.tensor([kf.frame_index for kf in self.odometry.keyframes], dtype=torch.long),
            loops=list(self._loops), queries=list(self._queries), graph=graph, optimization=opt,
            num_frames=len(self._frames), num_keyframes=len(self._kf_poses), num_lost=self._num_lost,
            num_skipped=self._num_skipped, timings=self.timer.summary())
