"""The run loop (:func:`run_slam`): every frame read (decoded ahead in threads) and tracked, the new keyframes'
points computed in a map worker, the loop work in the system's loop worker, then the final optimisation.
"""
from __future__ import annotations

import functools
import itertools
import logging
import os
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from slam.config import SLAMConfig, UsageError, check_sequence_intrinsics
from slam.io.images import FrameReadError
from slam.io.sequence import RGBDSequence, SequenceView
from slam.io.trajectory import Trajectory
from slam.mapping import PointCloudMap
from slam.odometry.features import extract_features
from slam.report import RunReport
from slam.system import RGBDSLAM, LoopWorkerError, SLAMResult
from slam.threads import limit_threads

logger = logging.getLogger(__name__)

__all__ = ["RunResult", "camera_of", "map_reference", "run_slam", "unmatched_groundtruth"]


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
        report: its :class:`slam.report.RunReport` (``metrics.json``), set by :func:`slam.report.evaluate_run`.
        loop_curves: ``{"before_verification": PRCurve, "after_verification": PRCurve}`` (with ground truth,
            filled by :func:`slam.report.evaluate_run`).
        config: the config the run used.
        frame_step: every ``frame_step``-th input frame was used.
        map: the keyframes' points (:class:`slam.mapping.PointCloudMap`), None when the map is off.
        map_cloud: the merged map ``(points (N, 3) float32, colours (N, 3) uint8)`` placed with the final
            keyframe poses (filled by :func:`slam.report.evaluate_run`).
        backbone: the descriptor's backbone as built (None without loop closure).
        descriptor_dim: the size of its descriptors (None without loop closure).
        relocalisation: the :class:`slam.maps.RelocalisationReport` of a run in a saved map (``map_dir``).
        map_origin: ``(7,)`` ground truth of the saved map's origin, if known.
        saved_map: where ``save_map`` wrote the run's map.
        camera: ``{"name": "fr2" / "calibration.txt" / None, "intrinsics": [fx, fy, cx, cy]}``.
        groundtruth_note: why no frame has ground truth when the sequence has a file of it.
        first_untracked: why the first frame that was lost or unreadable was.
    """

    result: SLAMResult
    sequence_name: str
    wall_seconds: float
    fps: float
    groundtruth: Trajectory | None
    gt_poses_per_frame: torch.Tensor | None
    report: RunReport | None = None
    loop_curves: dict[str, object] = field(default_factory=dict)
    config: SLAMConfig | None = None
    frame_step: int = 1
    map: PointCloudMap | None = None
    backbone: str | None = None
    descriptor_dim: int | None = None
    map_cloud: tuple[np.ndarray, np.ndarray] | None = None
    relocalisation: object | None = None
    map_origin: torch.Tensor | None = None
    saved_map: Path | None = None
    camera: dict | None = None
    groundtruth_note: str | None = None
    first_untracked: str | None = None


def _running(jobs: list) -> list:
    """The jobs not yet done; a finished job's error is raised here (the map's error is the run's), so that the
    list stays as long as the worker's backlog, not the run."""
    running = []
    for job in jobs:
        if job.done():
            job.result()
        else:
            running.append(job)
    return running


def run_slam(sequence: RGBDSequence, config: SLAMConfig | None = None, max_frames: int | None = None,
             progress: bool | None = None, descriptor: torch.nn.Module | None = None, frame_step: int = 1,
             frames: tuple[int, int] | None = None, save_map: str | os.PathLike | None = None, map_dir=None,
             observer=None) -> RunResult:
    """Track every frame of ``sequence`` (or every ``frame_step``-th) and optimise, with ``config.threads``
    threads (:func:`slam.threads.limit_threads`). A frame that cannot be read is skipped with a warning and placed
    by constant velocity.

    Args:
        sequence: an opened sequence (:func:`slam.io.open_sequence`).
        config: :class:`slam.config.SLAMConfig` (frozen, checked when built).
        max_frames: use only the first ``max_frames`` input frames.
        progress: a tqdm progress bar on stderr (None: when stderr is a terminal).
        descriptor: a prebuilt descriptor model (else built from the config).
        frame_step: use input frames ``0, N, 2N, ...`` of those (the trajectory and metrics are on them).
        frames: ``(start, end)``: the recording is input frames ``start .. end - 1`` only, re-numbered from
            0 (``max_frames`` and ``frame_step`` then apply to them).
        save_map: a folder to save the run's map in (:mod:`slam.maps`); with ``map_dir``, the saved map grown
            by this recording when it relocalised, else its own map.
        map_dir: a saved map (its folder, or a :class:`slam.maps.SavedMap`) to relocalise this recording in
            (``run.relocalisation`` says whether it did); with ``config.relocalisation.localize`` only localised.
        observer: called as ``observer.frame(frame, state, slam)`` after each frame (``frame`` None when unreadable)
            and ``observer.finish(result)`` at the end (:class:`slam.viewer.RunViewer`).

    Returns:
        :class:`RunResult`.

    Raises:
        ValueError: nothing to process, a ``frame_step`` < 1, a config that would give NaN poses
            (:class:`slam.config.UsageError`), intrinsics that cannot be a camera, or localisation
            (``config.relocalisation.localize``) without ``map_dir`` or with ``save_map``.
        FloatingPointError: the run produced non-finite poses (never silently returned).
        slam.maps.MapMismatchError: ``map_dir`` made with another descriptor, feature detector or camera rig,
            or (with ``save_map``) keyframe images of another size.
    """
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
        return _run(sequence, config, max_frames, progress, descriptor, frame_step, frames, save_map, map_dir,
                    observer)


def _run(sequence: RGBDSequence, config: SLAMConfig, max_frames: int | None, progress: bool | None,
         descriptor: torch.nn.Module | None, frame_step: int, frames: tuple[int, int] | None,
         save_map, map_dir, observer) -> RunResult:
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
    # loop work in a worker thread, except in a saved map (the relocaliser reads the loop closer every frame);
    # keyframe images are kept only for a map to save
    localize = config.relocalisation.localize
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
    bar = tqdm(range(n), desc=sequence.name, unit="frame", mininterval=0.2, disable=None if progress is None
               else not progress)
    # the reader threads decode ahead and extract each frame's features; an unreadable frame comes as its error
    ahead = functools.partial(_features_ahead, config.odometry.features)
    frames = view.frames(on_error="yield", prefetch=2, then=ahead)
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
            frame = None
            if isinstance(frame_or_error, FrameReadError):
                state = slam.skip(i, float(stamps[i]), str(frame_or_error))
            else:
                frame, features = frame_or_error
                state = slam.track(frame, features=features)
                if cloud is not None:
                    recent.append(frame)
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
            if observer is not None:
                observer.frame(frame, state, slam)
            if first_untracked is None and state.status in ("lost", "skipped"):
                first_untracked = f"frame {i} {state.status}: {state.reason}"
            if i % 10 == 0:
                map_jobs = _running(map_jobs)
                bar.set_postfix_str(f"kf={len(slam.keyframes)} loops={len(slam.loops)}"
                                    + ("" if reloc is None else f" in_map={'yes' if reloc.relocalised else 'no'}"),
                                    refresh=False)
        result = slam.finish()
        for job in map_jobs:
            job.result()  # a map error is the run's error
    except LoopWorkerError as exc:  # the run stops; what was tracked is still returned (exc.run) to be written
        failure = exc
        result = slam.result_so_far()
        logger.error("%s: %s; stopped after %d frames", sequence.name, exc, result.num_frames)
    finally:
        bar.close()
        if map_worker is not None:
            map_worker.shutdown(wait=True, cancel_futures=True)
    report = None
    if reloc is not None and failure is None:
        result, report = reloc.finish(result)
    if observer is not None:
        observer.finish(result)
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

        grown = reloc is not None and report.relocalised
        target = save_map
        if reloc is not None and not grown and saved.path is not None and _same_folder(save_map, saved.path):
            # not placed in the map it was to grow in place: the map stays, this recording's goes beside it
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
    for k in itertools.count(1):
        candidate = path.with_name(path.name + suffix + ("" if k == 1 else f"-{k}"))
        if not candidate.exists():
            return candidate


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


def _features_ahead(config, frame):
    """``(frame, features)`` in a reader thread (None when extraction fails: the tracking thread then extracts
    again and reports the frame as lost with the error)."""
    try:
        return frame, extract_features(frame.rgb, frame.depth, frame.K, config)
    except (ValueError, TypeError, cv2.error):
        return frame, None


def _add_keyframes_to_map(cloud: PointCloudMap, slam: RGBDSLAM, new_ids: list[int], recent) -> None:
    """Back-project the frames that just became keyframes (this frame, or a promoted earlier one)."""
    by_index = {int(f.index): f for f in recent}
    with slam.timer("map"):
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
