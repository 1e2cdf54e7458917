"""Run the SLAM system over a sequence, evaluate it and write the standard outputs.

The command line (:mod:`slam.cli`) and the examples only parse arguments and call these functions.

Outputs written by :func:`write_outputs` into a folder:

* ``trajectory.txt``: TUM format, one pose per input frame, in input order;
* ``loops.txt``: one accepted loop per line, ``timestamp_a timestamp_b`` (the two keyframes' own stamps);
* ``metrics.json``: ``ate_rmse`` (null with ``ate_unavailable`` saying why when there is nothing to
  evaluate), ``num_loops``, ``fps``, the backbone used and more; valid JSON (no NaN or Infinity: a value
  that is not finite is written as null and named in ``non_finite``);
* ``trajectory.png``: the estimate (and ground truth) seen from above with the loop edges;
* ``map.ply``: the keyframes' coloured points placed with the optimised poses (:mod:`slam.mapping`).

Each file is written under a temporary name in the same folder and renamed into place, so a reader never
sees half a file; :func:`prepare_output_dir` checks the folder before a run and removes the previous
run's outputs, so that files left after a failed run are never the previous run's looking current.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import logging
import math
import os
import tempfile
import time
import uuid
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from slam.config import SLAMConfig
from slam.io.images import FrameReadError
from slam.io.sequence import RGBDSequence, SequenceView
from slam.io.trajectory import Trajectory, write_tum_trajectory
from slam.mapping import PointCloudMap, write_ply
from slam.progress import Progress
from slam.system import RGBDSLAM, LoopWorkerError, SLAMResult
from slam.threads import limit_threads

logger = logging.getLogger(__name__)

__all__ = ["OUTPUT_FILES", "OutputDirError", "RunResult", "evaluate_run", "json_safe", "loop_ground_truth_for_step",
           "loop_worker_metrics",
           "prepare_output_dir", "run_slam", "write_outputs"]

#: The files a run writes into its output folder (``map.ply`` unless the map is off).
OUTPUT_FILES = ("trajectory.txt", "loops.txt", "metrics.json", "trajectory.png", "map.ply")


class OutputDirError(OSError):
    """The output folder cannot take a run's outputs (a file, not writable, or an output name taken)."""


@dataclass
class RunResult:
    """A finished run: the system's result plus wall-clock figures.

    Attributes:
        result: :class:`slam.system.SLAMResult`.
        sequence_name: name of the sequence.
        wall_seconds: time of the whole run (reading, tracking, loops, final optimisation).
        fps: input frames per second over ``wall_seconds``.
        groundtruth: per-frame ground truth (input order) or None.
        gt_poses_per_frame: ``(N, 7)`` ground truth of each processed frame (NaN where unknown).
        metrics: filled by :func:`evaluate_run`.
        loop_curves: ``{"before_verification": PRCurve, "after_verification": PRCurve}`` (with ground truth).
        config: the config the run used.
        frame_step: every ``frame_step``-th input frame was used.
        map: the keyframes' points (:class:`slam.mapping.PointCloudMap`), None when the map is off.
        map_cloud: the merged map ``(points (N, 3) float32, colours (N, 3) uint8)`` placed with the final
            keyframe poses (filled by :func:`evaluate_run`).
        backbone: the descriptor's backbone as built (None without loop closure).
        descriptor_dim: the size of its descriptors (None without loop closure).
    """

    result: SLAMResult
    sequence_name: str
    wall_seconds: float
    fps: float
    groundtruth: Trajectory | None
    gt_poses_per_frame: torch.Tensor | None
    metrics: dict[str, object] = field(default_factory=dict)
    loop_curves: dict[str, object] = field(default_factory=dict)
    config: SLAMConfig | None = None
    frame_step: int = 1
    map: PointCloudMap | None = None
    backbone: str | None = None
    descriptor_dim: int | None = None
    map_cloud: tuple[np.ndarray, np.ndarray] | None = None
    relocalisation: object | None = None  # slam.maps.RelocalisationReport of a run in a saved map (map_dir)
    map_origin: torch.Tensor | None = None  # (7,) ground truth of the saved map's origin (map_dir), if known
    saved_map: Path | None = None  # where save_map wrote the run's map
    #: the sequence's camera: ``{"name": "fr2" / "calibration.txt" / None, "intrinsics": [fx, fy, cx, cy]}``
    camera: dict | None = None
    groundtruth_note: str | None = None  # why no frame has ground truth when the sequence has a file of it
    first_untracked: str | None = None  # why the first frame that was lost or unreadable was


def run_slam(sequence: RGBDSequence, config: SLAMConfig | None = None, max_frames: int | None = None,
             progress: bool | None = None, descriptor: torch.nn.Module | None = None,
             prefetch: int = 2, frame_step: int = 1, frames: tuple[int, int] | None = None,
             save_map: str | os.PathLike | None = None, map_dir=None) -> RunResult:
    """Track every frame of ``sequence`` (or every ``frame_step``-th) and optimise.

    A frame that cannot be read (missing or corrupt image) is skipped with a warning and placed by constant
    velocity, so the trajectory still has one pose per used frame. With ``config.map.enabled`` the
    keyframes' coloured points are kept for ``map.ply`` (:class:`slam.mapping.PointCloudMap`). torch, BLAS
    and OpenCV compute with ``config.threads`` threads during the run (:func:`slam.threads.limit_threads`);
    the caller's counts are restored when it returns.

    Args:
        sequence: an opened sequence (:func:`slam.io.open_sequence`).
        config: :class:`slam.config.SLAMConfig` (frozen, checked when built).
        max_frames: use only the first ``max_frames`` input frames.
        progress: show a progress bar (None: when stderr is a terminal).
        descriptor: a prebuilt descriptor model (else built from the config).
        prefetch: frames decoded ahead in background threads.
        frame_step: use input frames ``0, N, 2N, ...`` of those (the trajectory and metrics are on them).
        frames: ``(start, end)``: the recording is input frames ``start .. end - 1`` only, re-numbered from
            0 (``max_frames`` and ``frame_step`` then apply to them).
        save_map: a folder to save the run's map in (:mod:`slam.maps`: keyframes, pose graph, index); with
            ``map_dir``, the saved map grown by this recording when it relocalised, else its own map (a
            recording whose keyframe images differ in size from the map's is refused at its first
            keyframe: a grown map holds one size).
        map_dir: a saved map (its folder, or a :class:`slam.maps.SavedMap`) to relocalise this recording
            in: every pose is then reported in the map's world, or, when it never relocalises, in its
            own (``run.relocalisation`` says which; ``config.relocalisation`` sets how). With
            ``config.relocalisation.localize`` the recording is only localised in it: no loops of its
            own, no map.ply, keyframes released once used (memory flat over any length), nothing saved.

    Returns:
        :class:`RunResult`.

    Raises:
        ValueError: nothing to process, a ``frame_step`` < 1, a config that would give NaN poses
            (:class:`slam.options.UsageError`), intrinsics that cannot be a camera, or localisation
            (``config.relocalisation.localize``) without ``map_dir`` or with ``save_map``.
        FloatingPointError: the run produced non-finite poses (never silently returned).
        slam.maps.MapMismatchError: ``map_dir`` made with another descriptor, feature detector or camera rig,
            or (with ``save_map``) keyframe images of another size.
    """
    from slam.options import UsageError, check_sequence_intrinsics

    config = config if config is not None else SLAMConfig()
    if not isinstance(config, SLAMConfig):
        raise TypeError(f"config must be a slam.config.SLAMConfig, got {type(config).__name__}")
    if config.relocalisation.localize and (map_dir is None or save_map is not None):
        raise UsageError("localisation only (config.relocalisation.localize) needs a saved map (map_dir) and saves "
                         "none (save_map)")
    if isinstance(frame_step, bool) or not isinstance(frame_step, (int, np.integer)) or frame_step < 1:
        raise ValueError(f"frame_step must be an integer >= 1, got {frame_step!r}")
    check_sequence_intrinsics(sequence)
    with limit_threads(config.threads):  # the caller's counts are restored when the run ends (or fails)
        return _run(sequence, config, max_frames, progress, descriptor, prefetch, frame_step, frames, save_map,
                    map_dir)


def _run(sequence: RGBDSequence, config: SLAMConfig, max_frames: int | None, progress: bool | None,
         descriptor: torch.nn.Module | None, prefetch: int, frame_step: int, frames: tuple[int, int] | None,
         save_map, map_dir) -> RunResult:
    if frames is not None:
        start, end = (int(v) for v in frames)
        if not 0 <= start < min(end, len(sequence)):
            raise ValueError(f"{sequence.name}: frames {start}:{end} select nothing of its {len(sequence)} frames")
        sequence = sequence[start:end]
    n_in = len(sequence) if max_frames is None else min(int(max_frames), len(sequence))
    if n_in <= 0:
        raise ValueError(f"{sequence.name}: nothing to process (max_frames={max_frames}, {len(sequence)} frames)")
    view = sequence[0:n_in:int(frame_step)]
    saved = None
    if map_dir is not None:
        from slam.maps import SavedMap, load_map

        saved = map_dir if isinstance(map_dir, SavedMap) else load_map(map_dir)
    if save_map is not None:
        from slam.maps import prepare_map_dir

        prepare_map_dir(save_map)
    n = len(view)
    stamps = view.timestamps
    # loop work in a worker thread (the same results; the relocaliser reads the loop closer after each frame,
    # so a run in a saved map keeps it in this thread)
    localize = config.relocalisation.localize
    # keyframe images are kept only for a map to save (capture_map stores them)
    slam = RGBDSLAM(config, descriptor=descriptor, background_loops=saved is None, localize=localize,
                    keep_images=save_map is not None)
    reloc = None
    if saved is not None:
        from slam.maps import MapRelocaliser

        reloc = MapRelocaliser(saved, slam, config.relocalisation)
    check_merge = reloc is not None and save_map is not None
    cloud = PointCloudMap.for_config(config) if config.map.enabled and not localize else None
    recent: deque = deque(maxlen=4)  # the frames a new keyframe can come from (this one or a promoted one)
    start = time.perf_counter()
    # decode ahead in threads; an unreadable frame comes as its FrameReadError, so it is only skipped
    bar = Progress(range(n), total=n, desc=sequence.name, enabled=progress)
    # the reader threads extract each frame's odometry features as they decode it (a pure function of the
    # frame: the same features as in the tracking thread, which then only matches and registers)
    ahead = _FeaturesAhead(config.odometry.features) if prefetch > 0 else None
    frames = view.frames(on_error="yield", prefetch=prefetch, then=ahead)
    # the keyframes' points are computed in a worker thread, in keyframe order (the map is only read at the end)
    map_worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="slam-map") if cloud is not None else None
    map_jobs = []
    dropped = 0  # the keyframes of slam.released whose points the map has been told to drop
    first_untracked = None
    failure = None
    try:
        for i in bar:
            with slam.timer("io_wait"):  # decoding runs ahead in threads: this is only the time waited for it
                frame_or_error = next(frames)
            if isinstance(frame_or_error, FrameReadError):
                state = slam.skip(i, float(stamps[i]), str(frame_or_error))
            else:
                features = None
                if ahead is not None:
                    frame_or_error, features = frame_or_error
                state = slam.track(frame_or_error, features=features)
                if cloud is not None:
                    recent.append(frame_or_error)
                    if state.new_keyframes:
                        map_jobs.append(map_worker.submit(_add_keyframes_to_map, cloud, slam, state.new_keyframes,
                                                          list(recent)))
                    released = slam.released[dropped:]  # revisits that added nothing (after their points' job)
                    if released:
                        map_jobs.append(map_worker.submit(cloud.drop, released))
                        dropped += len(released)
            if reloc is not None:
                if check_merge and slam.keyframes:  # a grown map holds one image size: refuse before the work
                    reloc.check_mergeable(slam.keyframes[0].rgb.shape)
                    check_merge = False
                reloc.observe(state)
            if first_untracked is None and state.status in ("lost", "skipped"):
                first_untracked = f"frame {i} {state.status}: {state.reason}"
            if i % 10 == 0:
                bar.set_postfix(f"kf={len(slam.keyframes)} loops={len(slam.loops)}"
                                + ("" if reloc is None else f" in_map={'yes' if reloc.relocalised else 'no'}"))
        result = slam.finish()
        for job in map_jobs:
            job.result()  # a map error is the run's error
    except LoopWorkerError as exc:  # the run stops; what was tracked is still returned (exc.run) to be written
        failure = exc
        result = slam.result_so_far()
        logger.error("%s: %s; stopped after %d frames", sequence.name, exc, result.num_frames)
    finally:
        if map_worker is not None:
            map_worker.shutdown(wait=True, cancel_futures=True)
    report = None
    if reloc is not None and failure is None:
        result, report = reloc.finish(result)
    wall = time.perf_counter() - start
    bad = ~torch.isfinite(result.trajectory.poses).all(dim=-1)
    if bool(bad.any()):
        first = int(torch.nonzero(bad)[0])
        raise FloatingPointError(f"{sequence.name}: {int(bad.sum())} of {n} poses are not finite (first: frame "
                                 f"{first}); check the settings and intrinsics")
    gt = view.groundtruth
    gt_note = None if gt is not None else unmatched_groundtruth(sequence, view.timestamps)
    gt_arr = torch.from_numpy(np.stack([
        p if p is not None else np.full(7, np.nan) for p in (view.groundtruth_pose(i) for i in range(result.num_frames))
    ])) if gt is not None else None
    closer = slam.loop_closer
    backbone = getattr(closer.descriptor, "backbone_name", None) if closer is not None else None
    descriptor_dim = getattr(closer.descriptor, "out_dim", None) if closer is not None else None
    saved_to = None
    if save_map is not None and failure is None:
        from slam.maps import capture_map
        from slam.maps import save_map as write_map

        # a run in a map it was placed in saves the grown map; otherwise (no map, or never relocalised)
        # its own, in its own world
        grown = reloc is not None and report.relocalised
        target = save_map
        if reloc is not None and not grown and saved.path is not None and _same_folder(save_map, saved.path):
            # asked to grow the map in place, but not placed in it: its own map there would replace every
            # earlier session by this recording alone. The map stays; this recording's goes beside it.
            target = _free_sibling(Path(save_map).resolve(), ".unplaced")  # "." has no name to extend
            logger.warning("%s: this recording was not placed in the map, which is kept as it was; its own map "
                           "goes into %s", save_map, target)
        saved_to = write_map(target, reloc.merged_map(view) if grown else capture_map(slam, view))
    run = RunResult(result, sequence.name, wall, result.num_frames / max(wall, 1e-9), gt, gt_arr, config=config,
                    frame_step=int(frame_step), map=cloud, backbone=backbone, descriptor_dim=descriptor_dim,
                    relocalisation=report, map_origin=None if saved is None else saved.groundtruth_origin,
                    saved_map=saved_to, camera=camera_of(sequence), groundtruth_note=gt_note,
                    first_untracked=first_untracked)
    if failure is not None:
        failure.run = run
        raise failure
    return run


def unmatched_groundtruth(sequence: RGBDSequence, stamps: np.ndarray) -> str | None:
    """Why frames stamped ``stamps`` have no ground truth when the sequence has a ground-truth file (a
    clock offset, another sequence's file); None when it has none."""
    reader = _reader_of(sequence)
    traj = getattr(reader, "groundtruth_trajectory", None)
    if traj is None or len(traj) == 0 or len(stamps) == 0:
        return None
    t = traj.timestamps.numpy()
    return (f"{reader.groundtruth_file} has {len(t)} poses ({t.min():.3f} to {t.max():.3f} s), none within "
            f"{getattr(reader, 'max_difference', 0.02):g} s of the {len(stamps)} frames used ({stamps.min():.3f} "
            f"to {stamps.max():.3f} s): a clock offset, or another sequence's ground truth?")


def _same_folder(a, b) -> bool:
    try:
        return Path(a).resolve() == Path(b).resolve()
    except OSError:
        return False


def _free_sibling(path: Path, suffix: str) -> Path:
    """``path`` + ``suffix`` (then ``-2``, ``-3`` ...): the first name beside ``path`` that does not exist."""
    k = 1
    while True:
        candidate = path.with_name(path.name + suffix + ("" if k == 1 else f"-{k}"))
        if not candidate.exists():
            return candidate
        k += 1


def _reader_of(sequence: RGBDSequence) -> RGBDSequence:
    # the sequence a view (seq[::2], seq[a:b]) was cut from: it holds the reader's camera and ground truth
    while isinstance(sequence, SequenceView):
        sequence = sequence.parent
    return sequence


def camera_of(sequence: RGBDSequence) -> dict:
    """The sequence's camera for reports: its name where the reader chose one (a TUM folder's fr1/fr2/fr3,
    ``ros``, ``calibration.txt``; None otherwise) and its intrinsics ``[fx, fy, cx, cy]``."""
    K = np.asarray(sequence.K, dtype=np.float64)
    return {"name": getattr(_reader_of(sequence), "camera_name", None),
            "intrinsics": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]}


class _FeaturesAhead:
    """``frame -> (frame, features)`` in a reader thread: :func:`slam.odometry.features.extract_features` with
    the run's settings (None when it fails: the tracking thread then extracts again and reports the frame
    as lost with the error, as without this)."""

    def __init__(self, config):
        self.config = config

    def __call__(self, frame):
        from slam.odometry.features import extract_features

        try:
            return frame, extract_features(frame.rgb, frame.depth, frame.K, self.config)
        except (ValueError, TypeError, cv2.error):
            return frame, None


def _add_keyframes_to_map(cloud: PointCloudMap, slam: RGBDSLAM, new_ids: list[int], recent) -> None:
    """Back-project the frames that just became keyframes (this frame, or a promoted earlier one)."""
    with slam.timer("map"):
        _add_to_map(cloud, slam, new_ids, recent)


def _add_to_map(cloud: PointCloudMap, slam: RGBDSLAM, new_ids: list[int], recent) -> None:
    by_index = {int(f.index): f for f in recent}
    for kf_id in new_ids:
        frame = by_index.get(int(slam.keyframes[kf_id].frame_index))
        if frame is None:  # not among the recent frames: the map misses this keyframe's points
            logger.debug("map: no image kept for keyframe %d (frame %d)", kf_id, slam.keyframes[kf_id].frame_index)
            continue
        try:
            cloud.add(kf_id, frame.rgb, frame.depth, frame.K, reference=map_reference(slam, kf_id))
        except ValueError as e:  # a frame odd enough for the map but not for tracking: leave its points out
            logger.warning("map: keyframe %d (frame %d) left out: %s", kf_id, frame.index, e)


def map_reference(slam: RGBDSLAM, kf_id: int):
    """``(parent id, its pose of keyframe kf_id)`` in the depth camera's frame (the map's), by the odometry edge
    that made the keyframe: what :meth:`slam.mapping.PointCloudMap.add` compares its points with; None for the
    first keyframe and after a tracking loss (a weak edge: a guess)."""
    if kf_id == 0:
        return None
    edge = slam.odometry.edges[kf_id - 1]
    return None if edge.weak else (edge.i, slam.depth_camera_pose(edge.T_ij))


def loop_ground_truth_for_step(frame_step: int = 1):
    """The default :class:`slam.eval.LoopGroundTruthConfig` for a run on every ``frame_step``-th frame.

    Its ``min_frame_gap`` (100 frames: 3.3 s at 30 Hz, what odometry links rather than a revisit) counts
    input frames; a run's frame indices are those of the frames it used, so the gap becomes
    ``ceil(100 / frame_step)`` of them: the same 3.3 s. Left at 100, a run at step 6 would need 20 s
    between a query and its match, and count the revisits 3-20 s apart, which the loop detector is
    right to find, as false detections.

    Example:
        >>> loop_ground_truth_for_step(6).min_frame_gap, loop_ground_truth_for_step(1).min_frame_gap
        (17, 100)
    """
    from slam.eval import LoopGroundTruthConfig

    base = LoopGroundTruthConfig()
    return dataclasses.replace(base, min_frame_gap=max(1, math.ceil(base.min_frame_gap / int(frame_step))))


def evaluate_run(run: RunResult, loop_gt=None) -> dict[str, object]:
    """Compute the metrics of a run (stored in ``run.metrics`` and returned).

    Keys: ``sequence``, ``num_frames``, ``frame_step``, ``num_keyframes``, ``num_loops``, ``num_lost``,
    ``num_skipped``, ``fps``, ``wall_seconds``, ``time_per_stage``, ``backbone`` (as built; null without
    loop closure), ``rig``, ``map`` (points of the merged map, keyframes, points and MB kept during the run); ``ate_rmse`` (rigid SE(3) alignment, TUM association) and ``ate``
    (statistics), ``ate_tracked`` (the same over the tracked frames only, without the lost and unreadable
    ones' interpolated poses), ``odometry_ate_rmse`` (before the pose graph), ``rpe_1frame`` / ``rpe_1s`` (translation
    m, rotation deg) and ``loops_true`` / ``loops_false`` (accepted loops judged by ground-truth distance
    and angle, :class:`slam.eval.LoopGroundTruthConfig`; ``loop_hypotheses_false``: the false ones among
    the verified loops by final status, beside ``loop_hypotheses``, all of them by status, and
    ``online_corrections``) when there is ground truth to evaluate against; ``loop_worker`` (its lag:
    :func:`loop_worker_metrics`) always, and ``error`` when the run stopped on a :class:`LoopWorkerError`;
    otherwise ``ate_rmse`` is None and ``ate_unavailable`` says why (no ground truth, fewer than 3
    frames with it, a camera that never moves, ...). A run never fails here for want of ground truth.
    ``num_tracked``: the frames placed by tracking (the first one included); ``status``: ``"ok"``, or
    ``"failed"`` when that is fewer than ``SLAMConfig.min_tracked_fraction`` of the frames, with
    ``failure`` saying so and why the first untracked frame was (:func:`write_outputs` then writes no
    trajectory).

    Args:
        run: a :class:`RunResult`.
        loop_gt: :class:`slam.eval.LoopGroundTruthConfig` for judging loops (default: its thresholds, the
            frame gap in the run's frames, :func:`loop_ground_truth_for_step`).
    """
    # the map's merge and the alignments with the run's thread count, as the run itself
    with limit_threads(run.config.threads if run.config is not None else None):
        return _evaluate(run, loop_gt)


def _evaluate(run: RunResult, loop_gt) -> dict[str, object]:
    from slam.eval import ate, is_true_loop, rpe
    from slam.options import describe_rig, rig_of

    res = run.result
    m: dict[str, object] = {
        "sequence": run.sequence_name,
        "num_frames": res.num_frames,
        "frame_step": run.frame_step,
        "num_keyframes": res.num_keyframes,
        "released_keyframes": len(res.released),  # revisits that added nothing: features, image and points dropped
        "num_loops": len(res.loops),
        "num_lost": res.num_lost,
        "num_skipped": res.num_skipped,
        "fps": round(run.fps, 3),
        "wall_seconds": round(run.wall_seconds, 3),
        "time_per_stage": res.timings,
        "backbone": run.backbone,
        # every verified loop by its final status (kept / inconsistent / switched_off), and the online
        # corrections (BackendConfig.optimize_on_loop): how many, and their milliseconds
        "loop_hypotheses": {s: sum(lp.status == s for lp in res.loop_hypotheses)
                            for s in ("kept", "inconsistent", "switched_off")},
        "online_corrections": {"count": len(res.corrections),
                               "total_ms": round(1000 * sum(c.seconds for c in res.corrections), 3),
                               "max_ms": round(1000 * max((c.seconds for c in res.corrections), default=0.0), 3)},
    }
    m["loop_worker"] = loop_worker_metrics(res, run.config)
    if res.error is not None:
        m["error"] = res.error  # the run stopped early: the outputs hold the frames tracked before it
    if run.config is not None:
        d = run.config.loop.descriptor
        recipe = dataclasses.asdict(d.recipe)
        m["descriptor"] = ({"preset": d.preset, "backbone": run.backbone, "requested_backbone": d.backbone,
                            "dim": run.descriptor_dim, "fusion": recipe["fusion"], "seed": d.seed,
                            "weights": None if d.weights is None else str(d.weights), "recipe": recipe}
                           if run.config.loop.enabled else None)
        m["rig"] = describe_rig(rig_of(run.config))
    if run.camera is not None:
        m["camera"] = run.camera
    if run.map is not None:
        run.map_cloud = run.map.points(res.keyframe_trajectory.poses)
        m["map"] = {"points": int(run.map_cloud[0].shape[0]), "keyframes": len(run.map),
                    "kept_points": run.map.num_points, "kept_mb": round(run.map.nbytes / 1e6, 3),
                    "voxel_size": run.map.config.voxel_size}
    if res.optimization is not None:
        opt = res.optimization
        m["pose_graph"] = {"keyframes": res.graph.num_poses, "edges": res.graph.num_edges,
                           "initial_chi2": opt.initial_chi2, "chi2": opt.chi2, "status": str(opt.status),
                           "iterations": opt.iterations}
    m["ate_rmse"] = None
    gt_len = 0 if run.groundtruth is None else len(run.groundtruth)
    tracked = res.num_frames - res.num_lost - res.num_skipped  # the first frame counts: it sets the origin
    m["num_tracked"] = tracked
    least = run.config.min_tracked_fraction if run.config is not None else SLAMConfig.min_tracked_fraction
    m["status"] = "ok" if tracked >= least * res.num_frames else "failed"
    if m["status"] == "failed":
        m["failure"] = (f"{tracked} of {res.num_frames} frames tracked ({res.num_lost} lost, {res.num_skipped} "
                        f"unreadable), fewer than {least:.0%} (SLAMConfig.min_tracked_fraction)"
                        + (f"; the first: {run.first_untracked}" if run.first_untracked else ""))
    if run.groundtruth is None:
        m["ate_unavailable"] = run.groundtruth_note or "the sequence has no ground truth"
    elif gt_len < 3:
        m["ate_unavailable"] = f"only {gt_len} frame(s) with ground truth (the alignment needs 3)"
    elif tracked <= 1:
        m["ate_unavailable"] = (f"no frame was tracked ({res.num_lost} lost, {res.num_skipped} unreadable of "
                                f"{res.num_frames}): nothing to align")
    elif float((run.groundtruth.poses[:, :3] - run.groundtruth.poses[:1, :3]).norm(dim=-1).max()) < 1e-6:
        m["ate_unavailable"] = "the ground-truth camera never moves: the alignment is not defined"
    else:
        try:
            a = ate(run.groundtruth, res.trajectory)
            odo = ate(run.groundtruth, res.odometry_trajectory).rmse
        except ValueError as e:  # e.g. a camera that never moves: the alignment is not defined
            m["ate_unavailable"] = f"ATE not computed: {e}"
        else:
            if not (math.isfinite(a.rmse) and math.isfinite(odo)):
                m["ate_unavailable"] = (f"the ATE is not finite ({a.rmse}, odometry {odo}): ground-truth "
                                        f"positions out of range?")
        if "ate_unavailable" not in m:
            m["ate_rmse"] = a.rmse
            m["ate"] = {"rmse": a.rmse, "mean": a.mean, "median": a.median, "std": a.std, "max": a.max,
                        "num_pairs": a.num_pairs}
            m["odometry_ate_rmse"] = odo
            # over the tracked frames alone (lost and unreadable ones are interpolated guesses): what a
            # system that writes tracked frames only (ORB-SLAM) would be scored on
            m["ate_tracked"] = None
            if res.tracked is not None:
                kept = torch.nonzero(res.tracked).flatten()
                try:
                    t = a if len(kept) == res.num_frames else ate(run.groundtruth, res.trajectory.subset(kept))
                    m["ate_tracked"] = {"rmse": t.rmse, "num_pairs": t.num_pairs}
                except ValueError as e:  # too few tracked frames with ground truth to align
                    m["ate_tracked"] = {"unavailable": str(e)}
    if m["ate_rmse"] is not None:
        for key, kw in (("rpe_1frame", {"delta": 1, "delta_unit": "frames"}),
                        ("rpe_1s", {"delta": 1.0, "delta_unit": "seconds"})):
            try:
                r = rpe(run.groundtruth, res.trajectory, **kw)
                m[key] = {"trans_rmse_m": r.translation.rmse, "rot_rmse_deg": r.rotation.rmse,
                          "num_pairs": int(r.pairs.shape[0])}
            except ValueError as e:  # too short for the delta
                m[key] = {"error": str(e)}
        cfg = loop_gt or loop_ground_truth_for_step(run.frame_step)
        m["loop_ground_truth"] = dataclasses.asdict(cfg)
        gt = run.gt_poses_per_frame
        # an accepted loop is judged by closeness alone (the frame-gap rule is for counting revisits)
        pairs = torch.tensor([[lp.frame_b, lp.frame_a] for lp in res.loops], dtype=torch.long).reshape(-1, 2)
        judged = is_true_loop(gt, pairs, dataclasses.replace(cfg, min_frame_gap=1))
        m["loops_true"] = int(judged.sum())
        m["loops_false"] = int((~judged).sum())
        hyp = res.loop_hypotheses
        pairs = torch.tensor([[lp.frame_b, lp.frame_a] for lp in hyp], dtype=torch.long).reshape(-1, 2)
        true_hyp = is_true_loop(gt, pairs, dataclasses.replace(cfg, min_frame_gap=1)).tolist()
        m["loop_hypotheses_false"] = {s: sum(lp.status == s and not t for lp, t in zip(hyp, true_hyp))
                                      for s in ("kept", "inconsistent", "switched_off")}
        m["loop_detection"] = loop_precision_recall(run, cfg)
    if run.relocalisation is not None:
        m["relocalisation"] = _relocalisation_metrics(run)
    run.metrics = m
    return m


def loop_worker_metrics(result: SLAMResult, config: SLAMConfig | None = None) -> dict[str, object]:
    """The loop worker's lag over a run (``metrics.json``'s ``loop_worker``): the keyframes whose loop work was
    waiting when each frame was tracked (:attr:`slam.system.RGBDSLAM.loop_lag`), its maximum and, per fifth of
    the run's frames, its maximum and mean; ``backlog`` is ``BackendConfig.loop_backlog`` (0: tracking waits
    for the worker, the outputs are deterministic; N: it runs up to N keyframes ahead).

    Example:
        >>> from types import SimpleNamespace
        >>> r = SimpleNamespace(loop_lag=torch.tensor([0, 1, 1, 0, 2, 0, 0, 1, 0, 3]))
        >>> m = loop_worker_metrics(r)
        >>> m["lag_max"], m["lag_per_fifth"]["max"], m["lag_per_fifth"]["mean"]
        (3, [1, 1, 2, 1, 3], [0.5, 0.5, 1.0, 0.5, 1.5])
    """
    lag = result.loop_lag if result.loop_lag is not None else torch.zeros(0, dtype=torch.int64)
    backlog = config.backend.loop_backlog if config is not None else None
    out: dict[str, object] = {"backlog": backlog,
                              "mode": None if backlog is None else ("waits" if backlog == 0 else "runs ahead"),
                              "lag_max": int(lag.max()) if lag.numel() else 0}
    parts = [p for p in torch.tensor_split(lag, 5) if p.numel()] if lag.numel() else []
    out["lag_per_fifth"] = {"max": [int(p.max()) for p in parts],
                            "mean": [round(float(p.double().mean()), 3) for p in parts]}
    return out


def _relocalisation_metrics(run: RunResult) -> dict[str, object]:
    """The map relocalisation's report, with the errors in the map's world without alignment when the map
    knows the ground truth of its origin (:func:`slam.maps.map_world_errors`)."""
    from slam.maps import map_world_errors

    rep = run.relocalisation.as_dict()
    rep["map_world_errors"] = None
    if run.relocalisation.relocalised and run.map_origin is not None and run.gt_poses_per_frame is not None:
        rep["map_world_errors"] = map_world_errors(run.result.trajectory.poses, run.gt_poses_per_frame,
                                                   run.map_origin)
    return rep


def loop_precision_recall(run: RunResult, config=None) -> dict[str, object]:
    """Precision/recall of the loop detector over the keyframe queries, before and after verification.

    Each query keyframe contributes its best candidate: before verification the most similar eligible
    keyframe scored by similarity; after verification the most similar *verified* candidate (queries with
    none score ``-inf``). Positives are the ground-truth revisits among the keyframes
    (:func:`slam.eval.ground_truth_loops`).

    Args:
        run: a :class:`RunResult`.
        config: :class:`slam.eval.LoopGroundTruthConfig` (default: :func:`loop_ground_truth_for_step`).

    Returns:
        ``{"before_verification": {...}, "after_verification": {...}}`` with ``max_recall_at_full_precision``,
        ``average_precision`` and ``num_positives``; the curves themselves go to ``run.loop_curves``.
    """
    from slam.eval import evaluate_loop_candidates

    cfg = config or loop_ground_truth_for_step(run.frame_step)
    res = run.result
    frames = res.keyframe_frames
    if run.gt_poses_per_frame is None or not res.queries:
        return {}
    # each verified pair's own similarity (verified: passed geometric verification, kept by the group or not)
    similarity = {(lp.kf_a, lp.kf_b): lp.similarity for lp in res.loop_hypotheses}
    before_pairs, before_scores, after_pairs, after_scores = [], [], [], []
    for q in res.queries:
        if q.top_kf < 0:
            continue
        before_pairs.append([int(frames[q.kf]), int(frames[q.top_kf])])
        before_scores.append(q.top_score)
        best = q.verified[0] if q.verified else q.top_kf  # candidates come most similar first
        after_pairs.append([int(frames[q.kf]), int(frames[best])])
        after_scores.append(similarity[(best, q.kf)] if q.verified else float("-inf"))
    if not before_pairs:
        return {}
    out: dict[str, object] = {}
    for name, pairs, scores in (("before_verification", before_pairs, before_scores),
                                ("after_verification", after_pairs, after_scores)):
        ev = evaluate_loop_candidates(torch.tensor(pairs), torch.tensor(scores, dtype=torch.float64),
                                      run.gt_poses_per_frame, cfg, mode="best_per_query", indices=frames)
        out[name] = ev.curve.to_dict()
        run.loop_curves[name] = ev.curve
    return out


def json_safe(value, path: str = "", bad: list[str] | None = None):
    """A copy of ``value`` that :func:`json.dumps` writes as valid JSON: non-finite floats become None.

    Args:
        value: dicts, lists, tuples, numbers (python, numpy, 0-d tensors), strings, None.
        path: the key path of ``value`` (for the report).
        bad: collects the key paths of the values that were not finite.

    Example:
        >>> bad = []
        >>> json_safe({"a": float("inf"), "b": [1.0, float("nan")]}, bad=bad), bad
        ({'a': None, 'b': [1.0, None]}, ['a', 'b[1]'])
    """
    if isinstance(value, dict):
        return {str(k): json_safe(v, f"{path}.{k}" if path else str(k), bad) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v, f"{path}[{i}]", bad) for i, v in enumerate(value)]
    if isinstance(value, torch.Tensor) and value.numel() == 1:
        value = value.item()
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bool) or value is None or isinstance(value, (int, str)):
        return value
    if isinstance(value, float):
        if math.isfinite(value):
            return value
        if bad is not None:
            bad.append(path)
        return None
    return str(value)


def _replace_atomically(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary file beside ``path`` and rename it into place (the umask's mode)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with open(tmp, "xb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def prepare_output_dir(out_dir: str | os.PathLike, names=OUTPUT_FILES, clear: bool = True) -> Path:
    """Check (and create) an output folder before a run, and remove the previous run's outputs.

    Done before the work starts, so that a folder that cannot take the outputs costs nothing, and a run
    that fails later leaves no earlier outputs looking like its own.

    Args:
        out_dir: the folder (created with its parents).
        names: the output file names that must be free for regular files.
        clear: remove existing regular files of those names.

    Raises:
        OutputDirError: ``out_dir`` is a file, cannot be created or written to, or an output name is taken
            by something other than a regular file (a folder, say); nothing is removed then.
    """
    out = Path(out_dir).expanduser()
    if out.exists() and not out.is_dir():
        raise OutputDirError(f"--out {out}: exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputDirError(f"--out {out}: cannot create the folder ({e.strerror or e})") from None
    try:
        fd, probe = tempfile.mkstemp(prefix=".write-test.", dir=out)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise OutputDirError(f"--out {out}: cannot write into the folder ({e.strerror or e})") from None
    taken = [n for n in names if (out / n).exists() or (out / n).is_symlink()]
    for name in taken:
        p = out / name
        if p.is_symlink() or not p.is_file():
            raise OutputDirError(f"{p}: an output name is taken by something that is not a regular file "
                                 "(a folder?); move it away or choose another --out")
    if clear:
        for name in taken:
            (out / name).unlink()
    return out


def write_outputs(run: RunResult, out_dir: str | os.PathLike, plot: bool = True,
                  map_ply: bool | None = None) -> Path:
    """Write ``trajectory.txt``, ``loops.txt``, ``metrics.json``, ``trajectory.png`` and ``map.ply`` into ``out_dir``.

    Each file is written to a temporary name and renamed; the folder is checked first
    (:func:`prepare_output_dir` without clearing), so a name taken by a folder fails before anything is
    written.

    A failed run (``metrics["status"] == "failed"``: fewer frames tracked than
    ``SLAMConfig.min_tracked_fraction``) writes ``metrics.json`` alone, with ``failure`` saying why, and
    removes the other outputs an earlier run left: poses that are constant-velocity guesses are no result.

    Args:
        run: an evaluated :class:`RunResult` (:func:`evaluate_run` is called if it was not).
        out_dir: created if needed.
        plot: also draw ``trajectory.png``.
        map_ply: write ``map.ply`` (default: when the run kept a map).

    Returns:
        the output folder.

    Raises:
        OutputDirError: the folder cannot take the outputs.
    """
    out = prepare_output_dir(out_dir, clear=False)
    if not run.metrics:
        evaluate_run(run)
    if run.metrics.get("status") == "failed":  # guessed poses are no result: metrics.json says what happened
        prepare_output_dir(out, clear=True)  # an earlier run's files would pass for this one's
        _replace_atomically(out / "metrics.json", (json.dumps(json_safe(run.metrics), indent=2, allow_nan=False)
                                                   + "\n").encode("utf-8"))
        return out
    res = run.result
    write_map = run.map is not None if map_ply is None else bool(map_ply)
    if write_map and run.map is None:
        raise ValueError("map_ply=True but the run kept no map (config.map.enabled was False)")
    # everything is computed before the first file is replaced
    traj_text = _tum_text(res.trajectory)
    loops_text = "# timestamp_a timestamp_b  (accepted loop closures between keyframes)\n" + "".join(
        f"{lp.timestamp_a:.6f} {lp.timestamp_b:.6f}\n" for lp in res.loops)
    ply = None
    if write_map:
        pts, cols = run.map_cloud if run.map_cloud is not None else run.map.points(res.keyframe_trajectory.poses)
        buf = io.BytesIO()
        write_ply(buf, pts, cols, comment=f"attnloop map of {run.sequence_name}: {len(run.map)} keyframes, "
                                          f"voxel {run.map.config.voxel_size:g} m, the trajectory's frame")
        ply = buf.getvalue()
    png = None
    if plot:
        from slam.eval import plot_trajectory

        loops = torch.tensor([[lp.timestamp_a, lp.timestamp_b] for lp in res.loops], dtype=torch.float64
                             ).reshape(-1, 2)
        ate_txt = f", ATE {run.metrics['ate_rmse'] * 100:.1f} cm" if run.metrics.get("ate_rmse") is not None else ""
        # aligned to the ground truth as the ATE is, unless the ATE found no alignment (it says why)
        img = plot_trajectory(None, res.trajectory, run.groundtruth, loops=loops,
                              align=run.metrics.get("ate_rmse") is not None,
                              title=f"{run.sequence_name}: {len(res.loops)} loops{ate_txt}")
        ok, enc = cv2.imencode(".png", img)
        if not ok:
            raise OSError("could not encode trajectory.png")
        png = enc.tobytes()
    bad: list[str] = []
    metrics = json_safe(run.metrics, bad=bad)
    if bad:
        metrics["non_finite"] = {"keys": bad, "reason": "not finite, written as null"}
    metrics_text = json.dumps(metrics, indent=2, allow_nan=False)
    _replace_atomically(out / "trajectory.txt", traj_text.encode("utf-8"))
    _replace_atomically(out / "loops.txt", loops_text.encode("utf-8"))
    if ply is not None:
        _replace_atomically(out / "map.ply", ply)
    if png is not None:
        _replace_atomically(out / "trajectory.png", png)
    _replace_atomically(out / "metrics.json", (metrics_text + "\n").encode("utf-8"))  # last: the run is complete
    return out


def _tum_text(traj: Trajectory) -> str:
    buf = io.StringIO()
    write_tum_trajectory(buf, traj)
    return buf.getvalue()
