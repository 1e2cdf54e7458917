"""The RGB-D SLAM system: odometry front end + attention-guided loop closure + pose-graph back end.

frame -> odometry -> keyframe -> loop closer -> keyframe graph -> back end -> trajectory; loops are optimised
online and tracking re-anchored (``BackendConfig.optimize_on_loop``), and only keyframes enter the graph (a frame
is its keyframe's pose times its pose in it). With ``background_loops`` a keyframe's loop work runs in a worker
thread, with the same results, reported one keyframe later: docs/pipeline.md ("What each stage does", "Long runs").

Example:
    >>> import numpy as np
    >>> from slam.io.frame import RGBDFrame
    >>> from slam.config import override
    >>> cfg = override(SLAMConfig(), {"loop.enabled": False})
    >>> slam = RGBDSLAM(cfg)
    >>> K = np.array([[525., 0, 319.5], [0, 525., 239.5], [0, 0, 1]])
    >>> state = slam.track(RGBDFrame(0, 0.0, np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64), np.float32), K))
    >>> state.status, state.corrected
    ('lost', False)
    >>> result = slam.finish()
    >>> result.trajectory.poses.shape, result.num_keyframes
    (torch.Size([1, 7]), 0)
"""
from __future__ import annotations

import dataclasses
import logging
import math
from array import array
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np
import torch

from slam.backend import BackendResult, PoseGraphBackend
from slam.config import SLAMConfig
from slam.graph import PoseGraph
from slam.graph.optimizer import OptimizationResult
from slam.io.frame import RGBDFrame, check_frame
from slam.io.trajectory import Trajectory
from slam.keyframe_graph import EdgeKind, GrowingArray, KeyframeGraph
from slam.lie import se3_between, se3_compose, se3_exp, se3_identity, se3_log
from slam.loop import LoopCloser, LoopClosure, LoopQuery, LoopUpdate
from slam.odometry import RGBDOdometry
from slam.odometry.depth_registration import depth_camera_poses, rig_pose
from slam.odometry.features import FrameFeatures
from slam.odometry.frontend import Keyframe, TrackStatus
from slam.timing import StageTimer

logger = logging.getLogger(__name__)
# unreadable frames listed one by one in the log (the rest only counted)
_LISTED_SKIPS = 3
Tensor = torch.Tensor

__all__ = ["FrameState", "LoopClosure", "LoopQuery", "LoopWorkerError", "RGBDSLAM", "SLAMResult"]


class LoopWorkerError(RuntimeError):
    """The loop worker failed on a keyframe's loop work (the graph is half-updated): raised by the call that
    finds it and by every later one, with the worker's exception as ``__cause__``. :meth:`RGBDSLAM.result_so_far`
    still gives the frames tracked so far, and the partial run's outputs can still be written.

    Attributes:
        keyframes: the ids of the keyframes whose work failed.
        run: the partial :class:`slam.pipeline.RunResult` (set by :func:`slam.pipeline.run_slam`), else None.
    """

    def __init__(self, message: str, keyframes=()):
        super().__init__(message)
        self.keyframes = list(keyframes)
        self.run = None


@dataclass
class FrameState:
    """What :meth:`RGBDSLAM.track` reports for one frame.

    Attributes:
        index: input order of the frame.
        timestamp: its timestamp.
        pose: ``(7,)`` float64 the system's current world-from-camera estimate of the depth camera (the
            frame of the input ``K``; see ``FeatureConfig.rgb_intrinsics`` for unregistered frames): its
            keyframe's corrected pose composed with the frame's pose in it when loops have been optimised
            online (``corrected``), else the odometry's.
        status: ``"initialized" | "ok" | "lost" | "recovered" | "skipped"``.
        reason: why it is lost / skipped / a keyframe ("" when plainly tracked).
        keyframe_id: the keyframe it is expressed relative to (-1 before the first keyframe).
        new_keyframes: ids of keyframes created by this call.
        new_loops: loops verified during this call and kept (consistent with the others).
        num_inliers: inliers of the registration that placed the frame (0 when none did).
        inlier_rmse: their 3D RMSE in metres (NaN when no registration placed the frame).
        odometry_pose: ``(7,)`` the same frame placed by odometry alone (the chain of odometry edges).
        corrected: ``pose`` includes the corrections of the loops optimised so far (False: it is
            ``odometry_pose``).
        correction: the online optimisation run during this call, if any.
    """

    index: int
    timestamp: float
    pose: Tensor
    status: str
    reason: str
    keyframe_id: int
    new_keyframes: List[int] = field(default_factory=list)
    new_loops: List[LoopClosure] = field(default_factory=list)
    num_inliers: int = 0
    inlier_rmse: float = math.nan
    odometry_pose: Optional[Tensor] = None
    corrected: bool = False
    correction: Optional[BackendResult] = None


@dataclass
class SLAMResult:
    """What :meth:`RGBDSLAM.finish` returns.

    Attributes:
        trajectory: one optimised pose per input frame, in input order; a frame lost (or skipped) between two
            tracked ones is interpolated between their optimised poses by time (during the run it was
            placed by constant velocity, as ``odometry_trajectory`` keeps it).
        odometry_trajectory: the same frames before pose-graph optimisation.
        keyframe_trajectory: optimised keyframe poses (timestamps of the keyframes).
        keyframe_frames: ``(M,)`` input index of each keyframe.
        loops: the loops in effect at the end: verified, in the consistent group, and not switched off by
            the back end's robust kernel.
        queries: one entry per loop-database query.
        graph: the optimised keyframe pose graph (None when there were no keyframes).
        optimization: the optimiser's result (None when nothing was optimised).
        num_frames, num_keyframes, num_lost, num_skipped: counts.
        timings: seconds and calls per stage.
        loop_hypotheses: every verified loop, with its final ``status`` (kept / inconsistent / switched_off).
        corrections: the online optimisations, in order: each one's status, iterations, seconds and chi2;
            only the last keeps its poses, loop weights and optimiser result (the earlier ones' are in the
            graph: over a long run they would grow with the square of its length).
        tracked: ``(N,)`` bool per frame: placed by tracking (not lost, not unreadable): the frames that a
            system which outputs tracked frames only (ORB-SLAM's trajectory files) would report.
        loop_lag: ``(N,)`` int64 per frame: the keyframes whose loop work was waiting (queued or running in
            the loop worker) when the frame's :meth:`RGBDSLAM.track` returned (zeros without the worker).
        released: the keyframes whose features and image were released (revisits that added nothing:
            ``LoopClosureConfig.release_revisits``), in order; their poses stay in the trajectory.
        error: why the run stopped early (:class:`LoopWorkerError`; :meth:`RGBDSLAM.result_so_far`), else
            None. Such a result holds the poses as tracking reported them, not optimised.
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
    loop_hypotheses: List[LoopClosure] = field(default_factory=list)
    corrections: List[BackendResult] = field(default_factory=list)
    tracked: Optional[Tensor] = None
    loop_lag: Optional[Tensor] = None
    released: List[int] = field(default_factory=list)
    error: Optional[str] = None


def interpolate_gaps(timestamps: Tensor, poses: Tensor, placed: Tensor) -> Tensor:
    """Poses ``(N, 7)`` whose frames not ``placed`` are interpolated by time between the nearest placed frames
    before and after them: ``P_a exp(s log(P_a^-1 P_b))``, ``s = (t - t_a) / (t_b - t_a)``; frames outside the
    first and last placed ones keep their poses.

    Args:
        timestamps: ``(N,)`` seconds, increasing.
        poses: ``(N, 7)`` float64.
        placed: ``(N,)`` bool.

    Example:
        >>> P = torch.tensor([[0.0, 0, 0, 0, 0, 0, 1], [5.0, 5, 5, 0, 0, 0, 1], [2.0, 0, 0, 0, 0, 0, 1]])
        >>> interpolate_gaps(torch.tensor([0.0, 1.0, 4.0]), P, torch.tensor([True, False, True]))[1, :3].tolist()
        [0.5, 0.0, 0.0]
    """
    n = poses.shape[0]
    idx = torch.arange(n)
    # the last placed frame at or before each frame, and the first at or after it (-1 / n: none)
    before = torch.cummax(torch.where(placed, idx, torch.full_like(idx, -1)), 0).values
    after = torch.flip(torch.cummin(torch.flip(torch.where(placed, idx, torch.full_like(idx, n)), [0]), 0).values, [0])
    gap = ~placed & (before >= 0) & (after < n)
    if not bool(gap.any()):
        return poses
    a, b = before[gap], after[gap]
    t, ta, tb = timestamps[gap], timestamps[a], timestamps[b]
    s = ((t - ta) / (tb - ta).clamp_min(1e-12)).clamp(0.0, 1.0).to(poses.dtype)
    step = se3_log(se3_between(poses[a], poses[b]))
    out = poses.clone()
    out[gap] = se3_compose(poses[a], se3_exp(s[:, None] * step))
    return out


class RGBDSLAM:
    """Attention-guided loop-closing RGB-D SLAM.

    Args:
        config: :class:`slam.config.SLAMConfig`.
        descriptor: a built model mapping ``(1, 3, H, W)`` uint8 images to ``(1, D)`` L2-normalised descriptors
            (default: :class:`attnloop.AttentionDescriptor` built from ``config.loop.descriptor``).
        background_loops: run each keyframe's loop work in a worker thread: the same results, loops reported
            one keyframe later (or up to ``BackendConfig.loop_backlog`` keyframes); :meth:`finish` waits for
            all of it, and a failure of it is raised as :class:`LoopWorkerError`.
        localize: localisation in a saved map (:class:`slam.maps.MapRelocaliser`): keyframes enter the graph
            but are neither described nor searched for loops here (:meth:`release_keyframe`).
        keep_images: keep each keyframe's downsized image (``Keyframe.rgb``) after its loop work (what a saved
            map stores); False drops it then.

    Call :meth:`track` once per frame in input order (or :meth:`skip` for a frame that could not be read),
    then :meth:`finish`.
    """

    def __init__(self, config: Optional[SLAMConfig] = None, descriptor: Optional[torch.nn.Module] = None,
                 background_loops: bool = False, localize: bool = False, keep_images: bool = True):
        self.config = config or SLAMConfig()
        self.localize = bool(localize)
        self.keep_images = bool(keep_images) or self.localize  # localisation releases them itself, once queried
        self.odometry = RGBDOdometry(self.config.odometry)
        self.timer = StageTimer()
        self.graph = KeyframeGraph()
        self.backend = PoseGraphBackend(self.config.backend, {
            EdgeKind.ODOMETRY: self.config.backend.odometry_information_scale,
            EdgeKind.LOOP: self.config.loop.information_scale})
        self.loop_closer: Optional[LoopCloser] = None
        if self.config.loop.enabled:
            self.loop_closer = LoopCloser(self.config.loop, descriptor=descriptor, timer=self.timer)
        # per frame: timestamp, its keyframe (-1: none yet), its pose there, whether tracking placed it
        self._frame_ts, self._frame_kf, self._frame_placed = array("d"), array("q"), array("b")
        self._frame_T = GrowingArray(np.float64, (7,))
        # revisits (LoopClosureConfig.release_revisits), released once no longer tracking's reference
        self._release = (self.loop_closer is not None and not self.localize and not keep_images
                         and self.config.loop.release_revisits)
        self._to_release: List[int] = []
        self.released: List[int] = []  # keyframes whose features and image were released, in order
        self._loop_of_edge: Dict[int, LoopClosure] = {}
        self._corrections: List[BackendResult] = []
        self._corrected = False  # the estimates include loop corrections
        self._num_lost = 0
        self._num_skipped = 0
        self._finished = False
        # the loop worker: the tracking thread never reads the graph while the worker may write it
        self._worker: Optional[ThreadPoolExecutor] = None
        if background_loops and self.loop_closer is not None and not self.localize:
            self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="slam-loops")
        self._jobs: deque = deque()  # (future, keyframe ids) handed to the worker, oldest first
        self._failure: Optional[LoopWorkerError] = None  # the worker failed: every later call raises it
        self._broken = False  # set by the worker thread when a job raised: the jobs queued after it do nothing
        self._lag = array("q")  # per frame: keyframes waiting for the worker when track() returned
        # (2, M, 7) per keyframe: its estimate and odometry pose as reported
        self._shown = torch.zeros(2, 0, 7, dtype=torch.float64)
        self._shown_corrected = False  # the shown estimates include loop corrections
        # unregistered frames: the front end tracks the colour camera, poses are reported for the depth camera
        feats = self.config.odometry.features
        self._T_rgb_depth = None
        if feats.rgb_intrinsics is not None and any(float(x) != 0.0 for x in feats.rgb_from_depth_translation):
            self._T_rgb_depth = rig_pose(feats.rgb_from_depth_translation)

    @property
    def keyframes(self) -> List[Keyframe]:
        """The odometry's keyframes (features and downsized RGB; None once :meth:`release_keyframe` dropped them)."""
        return self.odometry.keyframes

    def release_keyframe(self, kf_id: int) -> None:
        """Drop a keyframe's features and image in localisation (they become None), keeping its pose and edges.

        Raises:
            ValueError: ``kf_id`` is tracking's current reference keyframe, or the run closes loops among its
                own keyframes (any of them can be a loop candidate later).
        """
        if not self.localize and self.loop_closer is not None:
            raise ValueError("release_keyframe() is for localisation (RGBDSLAM(localize=True)): a run that closes "
                             "loops verifies candidates against every keyframe's features")
        kfs = self.odometry.keyframes
        if kf_id == len(kfs) - 1:
            raise ValueError(f"keyframe {kf_id} is tracking's reference: its features are still registered against")
        kfs[kf_id].features = None
        kfs[kf_id].rgb = None

    def keyframe_index(self):
        """The loop closer's :class:`attnloop.index.KeyframeIndex`: one descriptor per keyframe in its database, in
        keyframe order (empty when localising: nothing is entered); None without loop closure."""
        return None if self.loop_closer is None else self.loop_closer.detector.index

    @property
    def loops(self) -> List[LoopClosure]:
        """Loops in effect so far (verified, consistent, not switched off)."""
        return [lp for lp in self._hypotheses() if lp.status == "kept"]

    def _hypotheses(self) -> List[LoopClosure]:
        return self.loop_closer.hypotheses if self.loop_closer is not None else []

    @property
    def loop_lag(self) -> int:
        """Keyframes whose loop work is waiting in the loop worker (queued or running); 0 without it. With
        ``BackendConfig.loop_backlog = N`` it is at most N + the keyframes of one hand-over after a
        :meth:`track`."""
        return sum(len(ids) for fut, ids in self._jobs if not fut.done())

    def track(self, frame: RGBDFrame, features: Optional[FrameFeatures] = None) -> FrameState:
        """Process the next frame.

        Args:
            frame: :class:`~slam.io.frame.RGBDFrame` (RGB ``(H, W, 3)`` uint8, depth ``(H, W)`` metres).
            features: the frame's odometry features if extracted ahead (``extract_features(frame.rgb,
                frame.depth, frame.K, config.odometry.features)``, as :func:`slam.pipeline.run_slam` does).

        Returns:
            :class:`FrameState`. Bad frames (no depth, no texture) are a ``"lost"`` state, never an error.

        Raises:
            TypeError, ValueError: ``frame`` is not an ``RGBDFrame`` or a field is of the wrong type, shape or
                units (:func:`slam.io.check_frame`: depth in millimetres, a greyscale image, a torch tensor).
        """
        if self._finished:
            raise RuntimeError("track() called after finish(); create a new RGBDSLAM")
        if self._failure is not None:
            raise self._failure
        if not isinstance(frame, RGBDFrame):
            raise TypeError(f"track() takes a slam.io.RGBDFrame, got {type(frame).__name__}")
        check_frame(frame)  # again: a field set after construction (frame.depth = depth_mm) is an error too
        with self.timer("odometry"):
            res = self.odometry.track(frame, features)
        status = res.status.value
        if res.status is TrackStatus.LOST:
            self._num_lost += 1
        T_kf = res.T_kf_frame.detach().to(torch.float64).cpu()
        self._record(float(frame.timestamp), res.keyframe_id, T_kf, res.status is not TrackStatus.LOST)
        # every keyframe the front end created during this call (a promoted previous frame included)
        kfs = self.odometry.keyframes[self._shown.shape[1] if self._worker is not None else self.graph.num_keyframes:]
        new_keyframes = [kf.id for kf in kfs]
        new_loops, correction = self._keyframe_work(kfs) if self._worker is None else self._submit(kfs)
        self._lag.append(self.loop_lag)
        if res.keyframe_id >= 0:
            pose, odo = self._reported_poses(res.keyframe_id, T_kf)
        else:
            pose = odo = self.depth_camera_pose(res.pose.detach().to(torch.float64).cpu())
        return FrameState(int(frame.index), float(frame.timestamp), pose, status, res.reason,
                          res.keyframe_id, new_keyframes, [lp for lp in new_loops if lp.status == "kept"],
                          res.num_inliers, res.inlier_rmse, odo, self._reported_corrected(), correction)

    def _keyframe_work(self, kfs: List[Keyframe]):
        """New keyframes into the graph, loops closed, the graph corrected online: (kept loops, correction or None)."""
        new_loops, settled = [], True
        self._release_revisits(kfs[-1].id if kfs else -1)
        touched = [kf.id for kf in kfs]  # where the graph changed, in order: the online correction's window
        for kf in kfs:  # into the graph with its odometry edge (the front end's edges all end at a new keyframe)
            if kf.id == 0:
                self.graph.add_keyframe(kf.pose)
            else:
                edge = self.odometry.edges[kf.id - 1]
                if edge.j != kf.id:  # the graph's keyframe ids are the front end's: one edge per new keyframe
                    raise RuntimeError(f"odometry edge {edge.i} -> {edge.j} does not end at keyframe {kf.id}")
                self.graph.add_odometry(edge.i, edge.T_ij, edge.information, estimate=kf.pose, weak=edge.weak)
            if self.loop_closer is not None and not self.localize:
                update = self.loop_closer.close(kf, self.odometry.keyframes, self.graph,
                                                through_loops=self._corrected,
                                                min_loop_weight=self.config.backend.switch_off_weight,
                                                repeats=self._repeats if self._release else None)
                self._apply(update)
                new_loops.extend(lp for lp in update.new if lp.consistent)
                settled = settled and self._settled(update)
                touched += [k for lp in update.new + update.changed for k in (lp.kf_a, lp.kf_b)]
                if update.revisit:
                    self._to_release.append(kf.id)
            if not self.keep_images:  # described (or never to be): nothing reads it again
                kf.rgb = None
        correction = None
        if self.config.backend.optimize_on_loop and not settled:  # not settled: some update changed the graph
            correction = self._correct(touched)
        return new_loops, correction

    def _settled(self, update: LoopUpdate) -> bool:
        """Whether the estimate already satisfies ``update``: only new, settled kept loops on a corrected estimate."""
        if update.changed or not self._corrected:
            return not update
        return all(lp.settled for lp in update.new if lp.consistent)

    def _repeats(self, lp: LoopClosure) -> bool:
        """The loop joins its query to an earlier keyframe within the odometry's keyframe thresholds: tracking
        against that keyframe would have made no new one here (LoopClosureConfig.release_revisits)."""
        oc = self.config.odometry
        a, v = self.odometry.keyframes[lp.kf_a], lp.verification
        return (v is not None and v.distance <= oc.keyframe_translation and v.rotation_deg <= oc.keyframe_rotation_deg
                and v.num_inliers >= oc.keyframe_min_inliers
                and v.num_inliers / max(a.features.num_valid, 1) >= oc.keyframe_min_inlier_ratio)

    def _release_revisits(self, newest: int) -> None:
        """Release the revisits older than ``newest``: tracking's reference is a later one, nothing uses them again."""
        for k in [k for k in self._to_release if k < newest]:
            kf = self.odometry.keyframes[k]
            kf.features, kf.rgb = None, None
            self.released.append(k)
        self._to_release = [k for k in self._to_release if k >= newest]

    def _collect(self, keep: int):
        """Wait until at most ``keep`` keyframes' work is waiting and take the finished jobs' results, in order:
        (kept loops, the last correction, the graph's estimates after them or None)."""
        loops, correction, snapshot = [], None, None
        while self._jobs:
            fut, ids = self._jobs[0]
            if not fut.done() and self.loop_lag <= keep:
                break
            try:
                job_loops, job_correction, job_snapshot = fut.result()
            except Exception as exc:  # noqa: BLE001  (any error of the worker's; a Ctrl-C while waiting is not)
                self._jobs.popleft()
                self._failure = LoopWorkerError(f"the loop worker failed on keyframe{'s' if len(ids) > 1 else ''} "
                                                f"{', '.join(map(str, ids))}: {type(exc).__name__}: {exc}", ids)
                self._failure.__cause__ = exc
                raise self._failure
            self._jobs.popleft()
            loops.extend(job_loops)
            correction = job_correction if job_correction is not None else correction
            snapshot = job_snapshot
        return loops, correction, snapshot

    def _submit(self, kfs: List[Keyframe]):
        """Take the finished work (waiting beyond ``BackendConfig.loop_backlog``), hand ``kfs``' work to the worker."""
        if not kfs:
            return [], None
        new_loops, correction, snapshot = self._collect(keep=self.config.backend.loop_backlog)
        if snapshot is not None:
            est, odo, self._shown_corrected = snapshot
            self._shown = torch.stack([est, odo])
        self._chain_shown(self.odometry.keyframes[: kfs[-1].id + 1])
        ids = [kf.id for kf in kfs]
        self._jobs.append((self._worker.submit(self._background_work, list(kfs)), ids))
        return [lp for lp in new_loops if lp.status == "kept"], correction

    def _chain_shown(self, keyframes: List[Keyframe]) -> None:
        """Reported poses for ``keyframes`` beyond those shown: chained on their parent's by the odometry edge."""
        n = self._shown.shape[1]
        new: List[Tensor] = []  # (2, 7) each
        for kf in keyframes[n:]:
            if kf.id == 0:
                new.append(torch.stack([kf.pose, kf.pose]).to(torch.float64))
            else:
                edge = self.odometry.edges[kf.id - 1]
                parent = self._shown[:, edge.i] if edge.i < n else new[edge.i - n]
                new.append(se3_compose(parent, edge.T_ij.to(torch.float64).expand(2, 7)))
        if new:
            self._shown = torch.cat([self._shown, torch.stack(new, 1)], 1)

    def _background_work(self, kfs: List[Keyframe]):
        if self._broken:  # an earlier job failed: the graph is half-updated, nothing more is done on it
            raise RuntimeError("not run: an earlier keyframe's loop work failed")
        try:
            # chained again on the parent's pose as the last correction left it, as the tracking thread would
            for kf in kfs:
                if kf.id > 0:
                    edge = self.odometry.edges[kf.id - 1]
                    kf.pose = se3_compose(self.odometry.keyframes[edge.i].pose, edge.T_ij)
            loops, correction = self._keyframe_work(kfs)
            return loops, correction, (self.graph.estimates(), self.graph.odometry_poses(), self._corrected)
        except BaseException:
            self._broken = True
            raise

    def _reported_corrected(self) -> bool:
        return self._shown_corrected if self._worker is not None else self._corrected

    def keyframe_poses(self) -> Tensor:
        """``(M, 7)`` float64 the keyframes' poses (the depth camera's) as :meth:`track`'s reports place them now:
        corrected by the loops optimised so far, later keyframes chained by odometry (what a viewer draws)."""
        return self.depth_camera_pose(self._shown[0] if self._worker is not None else self.graph.estimates())

    def _reported_poses(self, kf_id: int, T: Tensor):
        """(pose, odometry pose) ``(7,)`` of the depth camera at ``T`` in keyframe ``kf_id``, as reports show them."""
        if self._worker is not None:
            est, odo = self._shown[0, kf_id], self._shown[1, kf_id]
        else:
            est, odo = self.graph.estimate(kf_id), self.graph.odometry_pose(kf_id)
        return self.depth_camera_pose(se3_compose(est, T)), self.depth_camera_pose(se3_compose(odo, T))

    def _apply(self, update: LoopUpdate) -> None:
        """Put the loop closer's decisions into the graph: new loop edges, and which loops are in effect."""
        for lp in update.new:
            lp.edge = self.graph.add_loop(lp.kf_a, lp.kf_b, lp.T_ab, lp.information)
            self._loop_of_edge[lp.edge] = lp
        for lp in update.new + update.changed:
            self.graph.edges[lp.edge].active = lp.consistent

    def _record_weights(self, result: BackendResult) -> None:
        thr = self.config.backend.switch_off_weight
        for e, w in result.loop_weights.items():
            self.graph.edges[e].weight = w
            lp = self._loop_of_edge[e]
            lp.weight = w
            lp.switched_off = w < thr

    def _correct(self, touched=()) -> Optional[BackendResult]:
        """Online correction: optimise, move the keyframes, re-anchor the front end on them.

        Args:
            touched: the keyframes where the graph changed (the new ones, the ends of the loops added or
                switched): the window's centres (``BackendConfig.online_window``).
        """
        if not self.graph.has_active_loop():
            if self._corrected:  # every loop left the group: back to odometry
                self.graph.set_estimates(self.graph.odometry_poses())
                self._reanchor()
                self._corrected = False
            return None
        with self.timer("online_correction"):
            free = self._online_window(touched)
            result = self.backend.optimize(self.graph, online=True, free=free)
            self.graph.set_estimates(result.poses)
            self._record_weights(result)
            self._reanchor(free)
        self._corrected = True
        if self._corrections:  # an earlier correction's poses are in the graph now: its figures are what is kept
            none = torch.zeros(0, 7, dtype=torch.float64)  # not a slice: a view would keep the (M, 7) block alive
            self._corrections[-1] = dataclasses.replace(self._corrections[-1], poses=none, loop_weights={},
                                                        optimization=None, history=[])
        self._corrections.append(result)
        logger.debug("online correction at keyframe %d: %d loops, chi2 %.3g -> %.3g in %d iterations, %.1f ms",
                    self.graph.num_keyframes - 1, len(result.loop_weights), result.initial_chi2, result.chi2,
                    result.iterations, 1000 * result.seconds)
        return result

    def _online_window(self, touched) -> Optional[List[int]]:
        """The keyframes an online correction moves: those within ``BackendConfig.online_window`` of a
        ``touched`` keyframe (in order of priority, while the window stays within ``2 (2 w + 1)`` keyframes)
        but keyframe 0, which fixes the world frame; None (the whole graph) when the window is off or full."""
        width, m = self.config.backend.online_window, self.graph.num_keyframes
        if width is None or not touched:
            return None
        free = torch.zeros(m, dtype=torch.bool)
        size, budget = 0, 2 * (2 * width + 1)
        for k in dict.fromkeys(touched):
            lo, hi = max(0, k - width), min(m, k + width + 1)
            added = hi - lo - int(free[lo:hi].sum())
            if size and size + added > budget:
                continue
            free[lo:hi] = True
            size += added
        if bool(free.all()):
            return None
        free[0] = False
        return torch.nonzero(free)[:, 0].tolist()

    def _reanchor(self, ids: Optional[List[int]] = None) -> None:
        """The front end's keyframes (or only ``ids``) take the graph's estimates: tracking continues from them."""
        est = self.graph.estimates()
        kfs = self.odometry.keyframes
        for k in (range(min(len(kfs), est.shape[0])) if ids is None else ids):
            kfs[k].pose = est[k].clone()

    def skip(self, index: int, timestamp: float, reason: str) -> FrameState:
        """Record a frame that could not be read: it is placed by constant velocity like a lost frame.

        Args:
            index: its input index.
            timestamp: its timestamp.
            reason: why it was skipped (logged and kept).
        """
        self._num_skipped += 1
        if self._num_skipped <= _LISTED_SKIPS:  # a folder of bad files is a few lines, not one per frame
            logger.warning("frame %d skipped: %s%s", index, reason, "" if self._num_skipped < _LISTED_SKIPS else
                           " (further unreadable frames are not listed; metrics.json counts them)")
        else:
            logger.debug("frame %d skipped: %s", index, reason)
        if self._frame_kf:
            kf_id, T = self._frame_kf[-1], torch.from_numpy(self._frame_T.view[-1].copy())
        else:
            kf_id, T = -1, se3_identity(dtype=torch.float64)
        self._record(float(timestamp), kf_id, T, False)
        self._lag.append(self.loop_lag)
        if kf_id >= 0:
            pose, odo = self._reported_poses(kf_id, T)
        else:
            pose, odo = T.clone(), T.clone()
        return FrameState(int(index), float(timestamp), pose, "skipped", reason, kf_id, odometry_pose=odo,
                          corrected=self._reported_corrected())

    def depth_camera_pose(self, poses: Tensor) -> Tensor:
        """Poses ``(..., 7)`` of the tracked camera (absolute, or relative: an odometry edge) as the depth
        camera's, the frame of every reported pose and of the map (the same poses for registered frames)."""
        if self._T_rgb_depth is None:
            return poses
        return depth_camera_poses(poses, self._T_rgb_depth)

    def _record(self, timestamp: float, kf_id: int, T_kf_frame: Tensor, placed: bool) -> None:
        self._frame_ts.append(timestamp)
        self._frame_kf.append(kf_id)
        self._frame_T.append(T_kf_frame.numpy())
        self._frame_placed.append(placed)

    def _placed(self) -> Tensor:
        """``(N,)`` bool: the frames placed by tracking (not lost, not skipped)."""
        return torch.tensor(self._frame_placed.tolist(), dtype=torch.bool)

    def _frames_trajectory(self, kf_poses: Tensor, interpolate_lost: bool = False) -> Trajectory:
        n = len(self._frame_ts)
        ts = torch.tensor(self._frame_ts.tolist(), dtype=torch.float64)
        kf = torch.tensor(self._frame_kf.tolist(), dtype=torch.long).clamp_min(0)
        T = torch.from_numpy(self._frame_T.view.copy())
        base = kf_poses[kf] if kf_poses.shape[0] else se3_identity(n, dtype=torch.float64)
        poses = se3_compose(base, T)
        if interpolate_lost:
            poses = interpolate_gaps(ts, poses, self._placed())
        return Trajectory(ts, self.depth_camera_pose(poses))

    def finish(self) -> SLAMResult:
        """Optimise the whole keyframe pose graph from the current estimates and return every frame's pose.

        Returns:
            :class:`SLAMResult`.
        """
        if self._failure is not None:
            raise self._failure
        self._finished = True
        if self._worker is not None:
            try:
                self._collect(keep=0)
            finally:
                self._worker.shutdown(wait=True)
        graph, opt = None, None
        kf_odo = self.graph.odometry_poses()
        kf_final = kf_odo
        if self.graph.has_active_loop():
            with self.timer("optimization"):
                result = self.backend.optimize(self.graph, online=False)
            self._record_weights(result)
            self.graph.set_estimates(result.poses)
            opt = result.optimization
            graph = opt.graph
            kf_final = result.poses
            logger.info("pose graph: %d keyframes, %d edges (%d loops in effect of %d verified), chi2 %.3g -> %.3g, %s",
                        graph.num_poses, graph.num_edges, len(self.loops), len(self._hypotheses()),
                        result.initial_chi2, result.chi2, result.status)
        elif self.graph.num_keyframes:
            self.graph.set_estimates(kf_odo)
            graph = self.graph.pose_graph(self.backend.information_scale)
        queries = self.loop_closer.queries if self.loop_closer is not None else []
        return self._result(kf_final, kf_odo, loops=self.loops, queries=queries, graph=graph, optimization=opt,
                            num_keyframes=self.graph.num_keyframes)

    def _result(self, kf_est: Tensor, kf_odo: Tensor, **fields) -> SLAMResult:
        """A :class:`SLAMResult` with every frame placed on the keyframe poses ``kf_est`` / ``kf_odo`` ``(M, 7)``."""
        kfs = self.odometry.keyframes
        kf_ts = torch.tensor([kf.timestamp for kf in kfs], dtype=torch.float64)
        lag = torch.tensor(self._lag.tolist(), dtype=torch.int64)
        if lag.numel() < len(self._frame_ts):  # a track() that raised LoopWorkerError recorded no lag
            lag = torch.cat([lag, torch.zeros(len(self._frame_ts) - lag.numel(), dtype=torch.int64)])
        return SLAMResult(
            trajectory=self._frames_trajectory(kf_est, interpolate_lost=True),
            odometry_trajectory=self._frames_trajectory(kf_odo),
            keyframe_trajectory=Trajectory(kf_ts, self.depth_camera_pose(kf_est.clone())),
            keyframe_frames=torch.tensor([kf.frame_index for kf in kfs], dtype=torch.long),
            num_frames=len(self._frame_ts), num_lost=self._num_lost, num_skipped=self._num_skipped,
            timings=self.timer.summary(), loop_hypotheses=self._hypotheses(), corrections=list(self._corrections),
            tracked=self._placed(), loop_lag=lag, released=list(self.released), **fields)

    def result_so_far(self) -> SLAMResult:
        """The frames tracked so far, placed as :meth:`track` reported them (no final optimisation), after a
        :class:`LoopWorkerError` (``SLAMResult.error`` says why); the work queued behind the failure is not run."""
        self._finished = True
        if self._worker is not None:
            self._worker.shutdown(wait=True, cancel_futures=True)
            self._jobs.clear()
        self._chain_shown(self.odometry.keyframes)
        est, odo = self._shown
        return self._result(est, odo, loops=self.loops, queries=[], graph=None, optimization=None,
                            num_keyframes=len(self.odometry.keyframes),
                            error=None if self._failure is None else str(self._failure))
